// The phantom: determinism, and that the truth it writes agrees with the slices it writes.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/math_constants.h"
#include "vispack/common/nrrd.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vp = vispack::pipeline;
namespace vph = vispack::phantom;
namespace fs = std::filesystem;
using nlohmann::json;
using vispack::test::bin;
using vispack::test::run_command;
using vispack::test::TempDir;

namespace {

// One tiny phantom with defects, generated once for the whole suite (about a second).
struct Phantom {
  TempDir dir{"vispack-phantom-test"};
  vph::PhantomSummary summary;
  json transforms;
  vispack::NrrdVolume rgb, ct, mask, labels;
  int width = 0, height = 0, slices = 0;
  double noise_sigma = 0;

  explicit Phantom(const std::string& preset, int slices_override = 0) {
    vph::PhantomOptions options;
    options.preset = preset;
    options.seed = 7;
    options.slices = slices_override;
    options.defects = true;
    options.quiet = true;
    summary = vph::make_phantom(dir.path(), options);
    transforms = json::parse(vispack::read_file(dir / "truth/transforms.json"));
    rgb = vispack::read_nrrd(dir / "truth/rgb.nrrd");
    ct = vispack::read_nrrd(dir / "truth/ct.nrrd");
    mask = vispack::read_nrrd(dir / "truth/mask.nrrd");
    labels = vispack::read_nrrd(dir / "truth/labels.nrrd");
    width = transforms["width"];
    height = transforms["height"];
    slices = static_cast<int>(transforms["slices"].size());
    noise_sigma = transforms["noise_sigma"];
  }

  std::string path(const std::string& sub) const { return dir / sub; }
  const json& slice(int k) const { return transforms["slices"][k]; }

  cv::Mat truth_rgb(int k) {
    return cv::Mat(height, width, CV_8UC3,
                   rgb.as<std::uint8_t>() + std::size_t(width) * height * 3 * k);
  }
  cv::Mat truth_ct(int k) {
    return cv::Mat(height, width, CV_16SC1,
                   ct.as<std::int16_t>() + std::size_t(width) * height * k);
  }
  cv::Mat truth_mask(int k) {
    return cv::Mat(height, width, CV_8UC1,
                   mask.as<std::uint8_t>() + std::size_t(width) * height * k);
  }
  cv::Mat truth_labels(int k) {
    return cv::Mat(height, width, CV_16UC1,
                   labels.as<std::uint16_t>() + std::size_t(width) * height * k);
  }
  std::string file(const std::string& stem, int k, const std::string& ext) const {
    char name_buffer[64];
    std::snprintf(name_buffer, sizeof name_buffer, "%s/%s_%04d%s", stem.c_str(), stem.c_str(), k,
                  ext.c_str());
    return dir / name_buffer;
  }
};

// The tiny preset (96×64×24, the unit-test size) for layout checks.
Phantom& tiny() {
  static Phantom phantom("tiny");
  return phantom;
}
// The small preset cut to 12 slices (the same anatomy, z compressed): structures span enough
// pixels for interior statistics (tiny's lungs are a dozen pixels across).
Phantom& small() {
  static Phantom phantom("small", 12);
  return phantom;
}

// The q → p matrix of docs/ARCHITECTURE.md: p = c + R(θ)(q − c) + d.
cv::Mat rigid_q_to_p(const json& s, double cx, double cy) {
  const double th = double(s["rotation_deg"]) * vispack::kPi / 180.0;
  const double c = std::cos(th), n = std::sin(th);
  const double dx = s["dx_px"], dy = s["dy_px"];
  cv::Mat m =
      (cv::Mat_<double>(2, 3) << c, -n, cx - c * cx + n * cy + dx, n, c, cy - n * cx - c * cy + dy);
  return m;
}

// Pixels whose label is constant over a (2r+1)² window (away from every boundary).
cv::Mat interior(const cv::Mat& labels16, int r) {
  cv::Mat lab;
  labels16.convertTo(lab, CV_32F);
  cv::Mat lo, hi;
  const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * r + 1, 2 * r + 1));
  cv::erode(lab, lo, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  cv::dilate(lab, hi, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  return lo == hi;
}

std::map<std::string, std::string> folder_bytes(const std::string& root) {
  std::map<std::string, std::string> files;
  for (const auto& entry : fs::recursive_directory_iterator(root)) {
    if (!entry.is_regular_file()) continue;
    files[fs::relative(entry.path(), root).string()] = vispack::read_file(entry.path().string());
  }
  return files;
}

}  // namespace

// ------------------------------------------------------------------------------------------
TEST(PhantomCli, HelpAndUsageErrors) {
  std::string out;
  EXPECT_EQ(run_command(bin("vispack-phantom") + " --help", &out), 0);
  EXPECT_NE(out.find("--preset"), std::string::npos);
  TempDir dir;
  EXPECT_EQ(run_command(bin("vispack-phantom") + " --out " + (dir / "x") + " --preset huge", &out),
            2);
  EXPECT_NE(out.find("huge"), std::string::npos) << out;
  EXPECT_EQ(run_command(bin("vispack-phantom") + " --preset tiny", &out), 2) << out;
  EXPECT_EQ(run_command(bin("vispack-phantom") + " --out " + (dir / "x") +
                            " --preset tiny --slices 3 --defects",
                        &out),
            2)
      << out;
  EXPECT_EQ(run_command(bin("vispack-phantom") + " --out " + (dir / "x") + " --bogus", &out), 2);
  EXPECT_FALSE(fs::exists(dir / "x/truth/transforms.json"));
}

TEST(PhantomCli, SameSeedIsByteIdenticalOtherSeedDrifts) {
  TempDir dir;
  const std::string cmd = bin("vispack-phantom") + " --quiet --preset tiny --out ";
  std::string out;
  ASSERT_EQ(run_command(cmd + (dir / "a") + " --seed 7", &out), 0) << out;
  ASSERT_EQ(run_command(cmd + (dir / "b") + " --seed 7 --threads 1", &out), 0) << out;
  ASSERT_EQ(run_command(cmd + (dir / "c") + " --seed 8", &out), 0) << out;
  const auto a = folder_bytes(dir / "a"), b = folder_bytes(dir / "b");
  // 24 rgb + 24 ct + 24 seg + 5 nrrd + transforms + palette + config.
  EXPECT_EQ(a.size(), 24u * 3 + 8);
  EXPECT_TRUE(a == b) << "same seed, different bytes";

  const json ta = json::parse(vispack::read_file(dir / "a/truth/transforms.json"));
  const json tc = json::parse(vispack::read_file(dir / "c/truth/transforms.json"));
  double difference = 0;
  for (int k = 0; k < 24; ++k) {
    difference += std::fabs(double(ta["slices"][k]["dx_px"]) - double(tc["slices"][k]["dx_px"]));
  }
  EXPECT_GT(difference / 24, 0.1);  // random walks of σ 0.3 px per step differ by far more
  EXPECT_NE(vispack::read_file(dir / "a/rgb/rgb_0005.png"),
            vispack::read_file(dir / "c/rgb/rgb_0005.png"));

  // Rerunning into a used folder with fewer slices leaves no stale slice behind.
  ASSERT_EQ(run_command(cmd + (dir / "a") + " --seed 7 --slices 5", &out), 0) << out;
  EXPECT_EQ(folder_bytes(dir / "a").size(), 5u * 3 + 8);
}

TEST(Phantom, LayoutAndTransformsFile) {
  Phantom& p = tiny();
  EXPECT_EQ(p.width, 96);
  EXPECT_EQ(p.height, 64);
  EXPECT_EQ(p.slices, 24);
  EXPECT_EQ(p.rgb.dims, (std::array<std::int64_t, 3>{96, 64, 24}));
  EXPECT_EQ(p.rgb.components, 3);
  EXPECT_EQ(p.ct.type, vispack::NrrdType::kInt16);
  EXPECT_EQ(p.labels.type, vispack::NrrdType::kUint16);
  EXPECT_DOUBLE_EQ(p.rgb.spacing_mm[0], 0.5);
  EXPECT_DOUBLE_EQ(p.rgb.spacing_mm[2], 1.0);
  EXPECT_DOUBLE_EQ(p.transforms["center_px"][0], 47.5);
  EXPECT_DOUBLE_EQ(p.transforms["center_px"][1], 31.5);
  // The output frame is the CT's (docs/ARCHITECTURE.md "The output frame"): no reference slice;
  // slice 0 carries the colour camera's constant offset like every other slice.
  EXPECT_EQ(p.transforms["frame"], "ct");
  EXPECT_TRUE(p.transforms["reference_slice"].is_null());
  const json& s0 = p.slice(0);
  const json& cam = p.transforms["camera_offset"];
  EXPECT_NEAR(double(s0["dx_px"]), double(cam["dx_px"]), 1e-6);
  EXPECT_NEAR(double(s0["dy_px"]), double(cam["dy_px"]), 1e-6);
  EXPECT_NEAR(double(s0["rotation_deg"]), double(cam["rotation_deg"]), 1e-6);
  EXPECT_GE(std::hypot(double(s0["dx_px"]), double(s0["dy_px"])), 2.5);  // tiny: ~3 px
  EXPECT_GE(std::fabs(double(s0["rotation_deg"])), 0.5);                 // tiny: 0.6..1.2°
  int jumps = 0;
  for (int k = 0; k < p.slices; ++k) {
    EXPECT_EQ(p.slice(k)["index"], k);
    EXPECT_EQ(p.slice(k)["file"], fs::path(p.file("rgb", k, ".png")).filename().string());
    if (p.slice(k)["jump"]) {
      ++jumps;
      EXPECT_EQ(k, p.summary.jump_slice);
      const double mx = double(p.slice(k)["dx_px"]) - double(p.slice(k - 1)["dx_px"]);
      const double my = double(p.slice(k)["dy_px"]) - double(p.slice(k - 1)["dy_px"]);
      EXPECT_GE(std::hypot(mx, my), 6.5);  // tiny preset: 7–9 px (above register.jump_px 6)
      EXPECT_GE(
          std::fabs(double(p.slice(k)["rotation_deg"]) - double(p.slice(k - 1)["rotation_deg"])),
          1.4);
    } else if (k > 0) {
      // Slow drift between neighbours: a step of σ 0.3 px never reaches 2 px in 24 draws.
      const double mx = double(p.slice(k)["dx_px"]) - double(p.slice(k - 1)["dx_px"]);
      const double my = double(p.slice(k)["dy_px"]) - double(p.slice(k - 1)["dy_px"]);
      EXPECT_LT(std::hypot(mx, my), 2.0) << k;
    }
  }
  EXPECT_EQ(jumps, 1);
  EXPECT_EQ(vispack::read_file(p.path("palette.json")).find("\"labels\""), 4u);
  const json palette = json::parse(vispack::read_file(p.path("palette.json")));
  EXPECT_GE(palette["labels"].size(), 4u);
}

TEST(Phantom, WarpingObservedSliceByItsTransformGivesTheTruth) {
  Phantom& p = small();
  const double cx = (p.width - 1) * 0.5, cy = (p.height - 1) * 0.5;
  int checked = 0;
  for (int k = 0; k < p.slices; ++k) {
    if (p.slice(k)["black"] || !p.slice(k)["duplicate_of"].is_null()) continue;
    const cv::Mat observed = vp::read_slice(p.file("rgb", k, ".png"));
    ASSERT_EQ(observed.type(), CV_8UC3);
    cv::Mat registered, identity;
    cv::warpAffine(observed, registered, rigid_q_to_p(p.slice(k), cx, cy), observed.size(),
                   cv::INTER_LINEAR | cv::WARP_INVERSE_MAP);
    cv::Mat regf;
    registered.convertTo(regf, CV_32FC3, 1.0 / double(p.slice(k)["gain"]));
    cv::Mat truthf;
    p.truth_rgb(k).convertTo(truthf, CV_32FC3);
    // Inside the body, 2 px or more from any label boundary (edges blend over one pixel and
    // bilinear interpolation mixes neighbours).
    const cv::Mat where = interior(p.truth_labels(k), 2) & (p.truth_mask(k) > 0);
    ASSERT_GT(cv::countNonZero(where), 500) << k;
    cv::Mat diff;
    cv::absdiff(regf, truthf, diff);
    const cv::Scalar mean = cv::mean(diff, where);
    const double mad = (mean[0] + mean[1] + mean[2]) / 3;
    // Tolerance: the sensor noise σ (3 levels). Bilinear interpolation averages the noise
    // (E|n| ≤ 0.8 σ) and adds a little texture smoothing; a wrong transform gives far more.
    EXPECT_LT(mad, p.noise_sigma) << "slice " << k;
    // Control: the same comparison without undoing the drift fails after the jump.
    if (k >= p.summary.jump_slice) {
      observed.convertTo(identity, CV_32FC3, 1.0 / double(p.slice(k)["gain"]));
      cv::absdiff(identity, truthf, diff);
      const cv::Scalar wrong = cv::mean(diff, where);
      EXPECT_GT((wrong[0] + wrong[1] + wrong[2]) / 3, 3 * p.noise_sigma) << "slice " << k;
    }
    ++checked;
  }
  EXPECT_EQ(checked, p.slices - 2);
}

TEST(Phantom, SegmentationUnderTheTransformEqualsTruthLabels) {
  Phantom& p = small();
  const json palette = json::parse(vispack::read_file(p.path("palette.json")));
  std::map<std::array<int, 3>, int> colour_to_id;
  colour_to_id[{0, 0, 0}] = 0;
  for (const auto& l : palette["labels"]) {
    colour_to_id[{int(l["colour"][0]), int(l["colour"][1]), int(l["colour"][2])}] = l["id"];
  }
  const double cx = (p.width - 1) * 0.5, cy = (p.height - 1) * 0.5;
  for (int k = 0; k < p.slices; ++k) {
    if (p.slice(k)["black"] || !p.slice(k)["duplicate_of"].is_null()) continue;
    const cv::Mat seg = vp::read_slice(p.file("seg", k, ".png"));
    cv::Mat registered;
    cv::warpAffine(seg, registered, rigid_q_to_p(p.slice(k), cx, cy), seg.size(),
                   cv::INTER_NEAREST | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT,
                   cv::Scalar(1, 2, 3));  // outside the observed frame: a colour in no palette
    const cv::Mat truth = p.truth_labels(k);
    const cv::Mat inner = interior(truth, 1);
    long same = 0, total = 0, unknown = 0, inner_same = 0, inner_total = 0;
    for (int y = 0; y < p.height; ++y) {
      for (int x = 0; x < p.width; ++x) {
        const cv::Vec3b c = registered.at<cv::Vec3b>(y, x);
        if (c == cv::Vec3b(1, 2, 3)) continue;
        const auto it = colour_to_id.find({c[0], c[1], c[2]});
        if (it == colour_to_id.end()) {
          ++unknown;  // PNG seg must hold exact palette colours only
          continue;
        }
        const bool ok = it->second == truth.at<std::uint16_t>(y, x);
        ++total;
        same += ok;
        if (inner.at<std::uint8_t>(y, x)) {
          ++inner_total;
          inner_same += ok;
        }
      }
    }
    EXPECT_EQ(unknown, 0) << k;
    // Nearest-neighbour resampling (seg drawn on the drifted grid, then pulled back) moves a
    // sample by up to 0.71 px, so only pixels right at a label boundary may flip: everywhere
    // else (3×3 neighbourhood of one label) ≥ 99.9 % agree, and ≥ 98 % of the whole frame.
    EXPECT_GE(double(inner_same) / double(inner_total), 0.999) << "slice " << k;
    EXPECT_GE(double(same) / double(total), 0.98) << "slice " << k;
    // Control: without undoing the drift, the slices after the jump disagree far more.
    if (k >= p.summary.jump_slice) {
      long raw_same = 0;
      for (int y = 0; y < p.height; ++y) {
        for (int x = 0; x < p.width; ++x) {
          const cv::Vec3b c = seg.at<cv::Vec3b>(y, x);
          const auto it = colour_to_id.find({c[0], c[1], c[2]});
          raw_same += it != colour_to_id.end() && it->second == truth.at<std::uint16_t>(y, x);
        }
      }
      EXPECT_LT(double(raw_same) / double(p.width * p.height), 0.95) << "slice " << k;
    }
  }
}

TEST(Phantom, CtMappedWithCtToRgbMatchesTruthCt) {
  Phantom& p = small();
  const json& m = p.transforms["ct_to_rgb"];
  const double s = m["scale"];
  EXPECT_NEAR(s, 0.9 / 0.33, 1e-6);  // CT pixel 0.9 mm / RGB pixel 0.33 mm
  const double th = double(m["rotation_deg"]) * vispack::kPi / 180.0;
  // Defined by the output frame (register.output_frame, identity in the config written).
  EXPECT_EQ(double(m["rotation_deg"]), 0.0);
  EXPECT_EQ(double(m["dx_px"]), 0.0);
  EXPECT_EQ(double(m["dy_px"]), 0.0);
  const double cx = (p.width - 1) * 0.5, cy = (p.height - 1) * 0.5;
  double ct_noise = p.transforms["ct_noise_hu"];
  for (int k = 0; k < p.slices; k += 3) {
    const cv::Mat stored = vp::read_slice(p.file("ct", k, ".png"));
    ASSERT_EQ(stored.type(), CV_16UC1);
    const double cct = (stored.cols - 1) * 0.5;
    cv::Mat hu;
    stored.convertTo(hu, CV_32F, 1.0, -1024.0);
    // u → q = c + s·R(θ)(u − c_ct) + d: warpAffine takes the source → destination matrix.
    auto q_from_u = [&](double rot, double dx, double dy) -> cv::Mat {
      const double c = std::cos(rot) * s, n = std::sin(rot) * s;
      return cv::Mat_<double>(2, 3) << c, -n, cx - c * cct + n * cct + dx, n, c,
             cy - n * cct - c * cct + dy;
    };
    cv::Mat mapped, wrong;
    cv::warpAffine(hu, mapped, q_from_u(th, m["dx_px"], m["dy_px"]), cv::Size(p.width, p.height));
    cv::warpAffine(hu, wrong, q_from_u(th + 2.0 * vispack::kPi / 180.0, 3.0, -3.0),
                   cv::Size(p.width, p.height));
    cv::Mat truth;
    p.truth_ct(k).convertTo(truth, CV_32F);
    // Flat regions only: labels constant within 1.5 CT pixels, and no CT edge (holder) nearby.
    cv::Mat lo, hi;
    const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(9, 9));
    cv::erode(truth, lo, kernel);
    cv::dilate(truth, hi, kernel);
    const cv::Mat where = interior(p.truth_labels(k), 4) & ((hi - lo) < 150);
    ASSERT_GT(cv::countNonZero(where), 1000);
    cv::Mat diff;
    cv::absdiff(mapped, truth, diff);
    const double mad = cv::mean(diff, where)[0];
    const double mad_all = cv::mean(diff)[0];
    // Tolerance: the CT noise σ (6 HU); bilinear interpolation only lowers it.
    EXPECT_LT(mad, ct_noise) << "slice " << k;
    // Control over the whole frame (edges included): the truth mapping gives ~30 HU (partial
    // volume differs at edges: CT pixels are 2.7× larger), a mapping off by 2° and 3 px more.
    cv::absdiff(wrong, truth, diff);
    EXPECT_GT(cv::mean(diff)[0], 2.5 * mad_all) << "slice " << k;
  }
}

TEST(Phantom, MaskLabelsAndAnatomy) {
  Phantom& p = small();
  for (int k = 0; k < p.slices; ++k) {
    const cv::Mat mask = p.truth_mask(k), labels = p.truth_labels(k), ct = p.truth_ct(k);
    const cv::Mat rgb = p.truth_rgb(k);
    // mask = labels > 0, by construction.
    EXPECT_EQ(cv::countNonZero((labels > 0) != (mask > 0)), 0) << k;
    cv::Mat channels[3];
    cv::split(rgb, channels);
    cv::Mat r16, g16, b16;
    channels[0].convertTo(r16, CV_16S);
    channels[1].convertTo(g16, CV_16S);
    channels[2].convertTo(b16, CV_16S);

    // Lungs: air in CT, inside the mask, enclosed: air reachable from the frame border never
    // touches them. The notch: air in CT too, open to the outside, outside the mask, blue in RGB.
    const cv::Mat lungs = labels == 5;
    if (k < p.slices - 1) {
      ASSERT_GT(cv::countNonZero(lungs), 20) << k;
      EXPECT_LT(cv::mean(ct, lungs)[0], -700) << k;  // lungs ≈ −800 HU
    }
    cv::Mat air = (ct < -400) / 255;
    cv::Mat outside = air.clone();
    cv::Mat flood = cv::Mat::zeros(p.height + 2, p.width + 2, CV_8U);
    cv::floodFill(outside, flood, cv::Point(0, 0), 2, nullptr, 0, 0, 4 | cv::FLOODFILL_MASK_ONLY);
    const cv::Mat reached = flood(cv::Rect(1, 1, p.width, p.height)) > 0;
    EXPECT_EQ(cv::countNonZero(reached & lungs), 0) << "lungs open to the outside at slice " << k;

    // The notch: mask-0 pixels inside the body's convex hull.
    std::vector<cv::Point> points;
    cv::findNonZero(mask, points);
    std::vector<cv::Point> hull;
    cv::convexHull(points, hull);
    cv::Mat in_hull = cv::Mat::zeros(p.height, p.width, CV_8U);
    cv::fillConvexPoly(in_hull, hull, 255);
    cv::erode(in_hull, in_hull, cv::Mat());  // not the hull's own rim
    const cv::Mat notch = in_hull & (mask == 0);
    ASSERT_GT(cv::countNonZero(notch), 3) << k;
    EXPECT_EQ(cv::countNonZero(notch & (labels > 0)), 0);
    EXPECT_EQ(cv::countNonZero(notch & ~reached), 0) << "notch not open to the outside at " << k;
    const cv::Mat blue = (b16 - r16) > 40;
    EXPECT_GT(cv::countNonZero(notch & blue), cv::countNonZero(notch) / 2) << k;

    // Tubes: green, outside the mask, fixed in the volume.
    const cv::Mat green = ((g16 - r16) > 50) & ((g16 - b16) > 50);
    ASSERT_GT(cv::countNonZero(green), 20) << k;
    EXPECT_EQ(cv::countNonZero(green & (mask > 0)), 0);
    // Each tube's centroid (left and right half of the frame) against slice 0.
    const cv::Mat green0 = [&] {
      cv::Mat c[3], r0, g0, b0;
      cv::split(p.truth_rgb(0), c);
      c[0].convertTo(r0, CV_16S);
      c[1].convertTo(g0, CV_16S);
      c[2].convertTo(b0, CV_16S);
      return cv::Mat(((g0 - r0) > 50) & ((g0 - b0) > 50));
    }();
    for (const cv::Rect half : {cv::Rect(0, 0, p.width / 2, p.height),
                                cv::Rect(p.width / 2, 0, p.width - p.width / 2, p.height)}) {
      const cv::Moments mo = cv::moments(green(half), true);
      const cv::Moments m0 = cv::moments(green0(half), true);
      ASSERT_GT(mo.m00, 10) << k;
      // Tolerance 0.1 px: edge pixels cross the colour threshold with the texture (±4 %
      // brightness, measured ≤ 0.05 px); a drifting tube would move with the random walk.
      EXPECT_NEAR(mo.m10 / mo.m00, m0.m10 / m0.m00, 0.1) << k;
      EXPECT_NEAR(mo.m01 / mo.m00, m0.m01 / m0.m00, 0.1) << k;
    }

    // Holder / table: plastic (100..300 HU) in the CT, outside the mask, not touching the body.
    const cv::Mat holder = (ct > 100) & (ct < 300) & (mask == 0);
    EXPECT_GT(cv::countNonZero(holder), 50) << k;
    cv::Mat grown;
    cv::dilate(mask, grown, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)));
    // "Solid" = above −300 HU: a pixel just outside the body edge blends to about −490 HU
    // (half coverage of air and tissue), a pixel of the holder is at +200.
    EXPECT_EQ(cv::countNonZero(grown & ((ct > -300) & (mask == 0))), 0)
        << "something solid within 2 px of the body outside the mask at slice " << k;
    // At least 4 structures besides background.
    double lo, hi;
    cv::minMaxLoc(labels, &lo, &hi);
    EXPECT_GE(hi, 4);
  }
  // Holder in the CT slices themselves.
  const cv::Mat ct0 = vp::read_slice(p.file("ct", 0, ".png"));
  EXPECT_GT(cv::countNonZero((ct0 > 1024 + 120) & (ct0 < 1024 + 280)), 20);
}

TEST(Phantom, BlackAndDuplicateSlicesAreWhereRecorded) {
  Phantom& p = tiny();
  int black = -1, duplicate = -1;
  for (int k = 0; k < p.slices; ++k) {
    if (p.slice(k)["black"]) black = k;
    if (!p.slice(k)["duplicate_of"].is_null()) {
      duplicate = k;
      EXPECT_EQ(p.slice(k)["duplicate_of"], k - 1);
    }
  }
  ASSERT_GE(black, 1);
  ASSERT_GE(duplicate, 1);
  EXPECT_EQ(black, p.summary.black_slice);
  EXPECT_EQ(duplicate, p.summary.duplicate_slice);
  for (int k = 0; k < p.slices; ++k) {
    const std::string bytes = vispack::read_file(p.file("rgb", k, ".png"));
    const cv::Mat image = vp::read_slice(p.file("rgb", k, ".png"));
    EXPECT_EQ(cv::countNonZero(image.reshape(1)) == 0, k == black) << k;
    if (k > 0) {
      const bool same = bytes == vispack::read_file(p.file("rgb", k - 1, ".png"));
      EXPECT_EQ(same, k == duplicate) << k;
      const bool seg_same = vispack::read_file(p.file("seg", k, ".png")) ==
                            vispack::read_file(p.file("seg", k - 1, ".png"));
      EXPECT_EQ(seg_same, k == duplicate) << k;
    }
  }
  EXPECT_DOUBLE_EQ(p.slice(duplicate)["dx_px"], p.slice(duplicate - 1)["dx_px"]);
}

TEST(Phantom, BodyStaysInsideTheObservedFrame) {
  for (Phantom* phantom : {&tiny(), &small()}) {
    Phantom& p = *phantom;
    for (int k = 0; k < p.slices; ++k) {
      const cv::Mat seg = vp::read_slice(p.file("seg", k, ".png"));
      cv::Mat any;
      cv::cvtColor(seg, any, cv::COLOR_RGB2GRAY);
      any = any > 0;
      const int border = cv::countNonZero(any.row(0)) + cv::countNonZero(any.row(p.height - 1)) +
                         cv::countNonZero(any.col(0)) + cv::countNonZero(any.col(p.width - 1));
      EXPECT_EQ(border, 0) << "body touches the frame at slice " << k;
    }
  }
}

TEST(Phantom, ConfigIsReadyAndDefinesTheCtFrame) {
  Phantom& p = tiny();
  const json config = json::parse(vispack::read_file(p.path("config.json")));
  EXPECT_EQ(config["rgb"]["pattern"], "rgb_{n}.png");
  EXPECT_EQ(config["spacing_mm"][0], 0.5);
  EXPECT_FALSE(config["register"].contains("ct_initial"));
  // The truth's ct_to_rgb is the config's definition of the output frame (never estimated):
  // scale = CT pixel / colour pixel, rotation and shift = register.output_frame.
  const json& frame = config["register"]["output_frame"];
  const json& truth = p.transforms["ct_to_rgb"];
  EXPECT_NEAR(double(truth["scale"]),
              double(config["ct"]["pixel_spacing_mm"][0]) / double(config["spacing_mm"][0]), 1e-9);
  EXPECT_NEAR(double(truth["rotation_deg"]), double(frame["rotation_deg"]), 1e-9);
  EXPECT_NEAR(double(truth["dx_px"]), double(frame["dx_px"]), 1e-9);
  EXPECT_NEAR(double(truth["dy_px"]), double(frame["dy_px"]), 1e-9);
  // The slices it names are there, in order.
  vp::SliceSource source;
  source.dir = p.path("rgb");
  source.pattern = config["rgb"]["pattern"];
  const auto files = vp::list_slices(source);
  ASSERT_EQ(files.size(), std::size_t(p.slices));
  EXPECT_EQ(files[10].number, 10);
}

TEST(Phantom, RawRgbAndJpegSegmentation) {
  // The raw planar RGB has the same pixels as the PNG of the same seed; JPEG seg is close.
  TempDir dir;
  vph::PhantomOptions options;
  options.preset = "tiny";
  options.seed = 3;
  options.slices = 6;
  options.quiet = true;
  vph::make_phantom(dir / "png", options);
  options.rgb_raw = true;
  options.seg_jpeg = true;
  vph::make_phantom(dir / "raw", options);
  const json config = json::parse(vispack::read_file(dir / "raw/config.json"));
  EXPECT_EQ(config["rgb"]["pattern"], "rgb_{n}.raw");
  EXPECT_EQ(config["rgb"]["raw"]["layout"], "planar");
  vp::RawLayout layout;
  layout.width = config["rgb"]["raw"]["width"];
  layout.height = config["rgb"]["raw"]["height"];
  layout.channels = 3;
  layout.planar = true;
  for (int k = 0; k < 6; ++k) {
    char name[64];
    std::snprintf(name, sizeof name, "rgb_%04d", k);
    const cv::Mat raw = vp::read_slice(dir / ("raw/rgb/" + std::string(name) + ".raw"), layout);
    const cv::Mat png = vp::read_slice(dir / ("png/rgb/" + std::string(name) + ".png"));
    EXPECT_EQ(cv::norm(raw, png, cv::NORM_INF), 0) << k;
    std::snprintf(name, sizeof name, "seg_%04d", k);
    const cv::Mat jpg = vp::read_slice(dir / ("raw/seg/" + std::string(name) + ".jpg"));
    const cv::Mat exact = vp::read_slice(dir / ("png/seg/" + std::string(name) + ".png"));
    cv::Mat diff;
    cv::absdiff(jpg, exact, diff);
    EXPECT_GT(cv::norm(diff, cv::NORM_INF), 0);  // JPEG is lossy: colours are noisy
    // but mostly close (quality 90): mean error of a few levels.
    EXPECT_LT(cv::mean(diff)[0], 8.0) << k;
  }
}

TEST(Phantom, LoadConfigAcceptsIt) {
  Phantom& p = tiny();
  const vp::Config config = vp::load_config(p.path("config.json"));
  EXPECT_EQ(config.rgb.dir, p.path("rgb"));
  ASSERT_TRUE(config.ct.has_value());
  EXPECT_DOUBLE_EQ(config.ct->pixel_spacing_mm[0], 1.0);
  ASSERT_TRUE(config.seg.has_value());
}

// The drift models that break the registration prior's assumption (a Gaussian walk): with the
// same seed the walk's draws are the same, so the rotation model is the walk plus exactly
// 0.02° per slice and the bowed one the walk plus exactly half a sine; the heavy model's steps
// have heavy tails (kurtosis far above the normal's 3); --jump-px sets the block jump's size.
namespace {

struct TruthWalk {
  std::vector<double> dx, dy, rot;
  int jump = -1;
};

TruthWalk truth_walk(const std::string& dir) {
  const json t = json::parse(vispack::read_file(dir + "/truth/transforms.json"));
  TruthWalk w;
  for (std::size_t k = 0; k < t["slices"].size(); ++k) {
    const json& s = t["slices"][k];
    w.dx.push_back(s["dx_px"]);
    w.dy.push_back(s["dy_px"]);
    w.rot.push_back(s["rotation_deg"]);
    if (s.value("jump", false)) w.jump = static_cast<int>(k);
  }
  return w;
}

TruthWalk drift_phantom(const TempDir& dir, const std::string& name,
                        vph::PhantomOptions::DriftModel model, bool jump = false,
                        double jump_min = 0, double jump_max = 0) {
  vph::PhantomOptions o;
  o.preset = "small";
  o.seed = 11;
  o.slices = 40;
  o.defects = false;
  o.jump = jump;
  o.drift_model = model;
  o.jump_px_min = jump_min;
  o.jump_px_max = jump_max;
  o.quiet = true;
  vph::make_phantom(dir / name, o);
  return truth_walk(dir / name);
}

double kurtosis(const std::vector<double>& v) {
  std::vector<double> d;
  for (std::size_t k = 1; k < v.size(); ++k)
    d.push_back(v[k] - v[k - 1]);
  double m2 = 0, m4 = 0;
  for (double x : d)
    m2 += x * x, m4 += x * x * x * x;
  m2 /= double(d.size()), m4 /= double(d.size());
  return m4 / (m2 * m2);
}

}  // namespace

TEST(PhantomDrift, ModelsThatAreNotTheSolversPrior) {
  using Model = vph::PhantomOptions::DriftModel;
  TempDir dir;
  const TruthWalk walk = drift_phantom(dir, "walk", Model::kWalk);
  const TruthWalk rotation = drift_phantom(dir, "rotation", Model::kRotation);
  const TruthWalk bowed = drift_phantom(dir, "bowed", Model::kBowed);
  const TruthWalk heavy = drift_phantom(dir, "heavy", Model::kHeavy);
  const std::size_t n = walk.dx.size();
  ASSERT_EQ(n, 40u);
  double rot_off = 0, bow_off = 0, bow_peak = 0;
  for (std::size_t k = 0; k < n; ++k) {
    rot_off = std::max(rot_off, std::fabs(rotation.rot[k] - walk.rot[k] - 0.02 * double(k)));
    EXPECT_DOUBLE_EQ(rotation.dx[k], walk.dx[k]) << k;
    const double bow = std::max(1.0, 0.02 * 192) * std::sin(vispack::kPi * double(k) / (n - 1));
    bow_off = std::max(bow_off, std::fabs(bowed.dx[k] - walk.dx[k] - bow));
    bow_off = std::max(bow_off, std::fabs(bowed.dy[k] - walk.dy[k] - bow));
    bow_peak = std::max(bow_peak, bowed.dx[k] - walk.dx[k]);
    EXPECT_DOUBLE_EQ(bowed.rot[k], walk.rot[k]) << k;
  }
  EXPECT_LT(rot_off, 1e-6);
  EXPECT_LT(bow_off, 1e-6);
  EXPECT_NEAR(bow_peak, 3.84, 0.01);  // 2 % of the small preset's 192 px height
  const double k_walk = kurtosis(walk.dx), k_heavy = kurtosis(heavy.dx);
  std::printf("step kurtosis: walk %.2f, heavy %.2f\n", k_walk, k_heavy);
  EXPECT_LT(k_walk, 4.5);
  EXPECT_GT(k_heavy, 6.0);

  // A block jump of 3..6 px (the jump's shift replaces that slice's walk step).
  const TruthWalk small_jump = drift_phantom(dir, "jump", Model::kWalk, true, 3, 6);
  ASSERT_GT(small_jump.jump, 0);
  const int j = small_jump.jump;
  const double size =
      std::hypot(small_jump.dx[j] - small_jump.dx[j - 1], small_jump.dy[j] - small_jump.dy[j - 1]);
  EXPECT_GE(size, 3.0);
  EXPECT_LE(size, 6.0);
}

TEST(PhantomCli, DriftModelAndJumpSizeErrors) {
  TempDir dir;
  const std::string cmd = bin("vispack-phantom") + " --quiet --preset tiny --out " + (dir / "p");
  std::string out;
  EXPECT_EQ(run_command(cmd + " --drift wobbly", &out), 2) << out;
  EXPECT_NE(out.find("--drift 'wobbly': not walk, heavy, rotation or bowed"), std::string::npos)
      << out;
  EXPECT_EQ(run_command(cmd + " --jump-px 6", &out), 2) << out;
  EXPECT_NE(out.find("--jump-px '6': expected MIN:MAX"), std::string::npos) << out;
  EXPECT_EQ(run_command(cmd + " --jump-px 6:3", &out), 2) << out;
  EXPECT_NE(out.find("needs 0 < MIN <= MAX <= 100 px"), std::string::npos) << out;
  EXPECT_EQ(run_command(cmd + " --drift heavy --jump-px 3:6", &out), 0) << out;
}

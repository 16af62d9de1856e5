// The presets that do not flatter registration (anatomy, anatomy-vhp): the anatomy really changes
// along z, there are no fiducials, the texture never repeats, drift can be switched off exactly,
// the CT is 2× coarser, and the truth still agrees with the slices written.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <set>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/common/nrrd.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vph = vispack::phantom;
namespace fs = std::filesystem;
using nlohmann::json;
using vispack::test::TempDir;

namespace {

constexpr int kSlices = 24;  // the anatomy preset spans its whole model whatever the length

struct Folder {
  TempDir dir{"vispack-anatomy"};
  vph::PhantomSummary summary;
  json transforms;
  vispack::NrrdVolume rgb, mask, labels;
  int W = 0, H = 0, N = 0;

  explicit Folder(vph::PhantomOptions o) {
    o.quiet = true;
    summary = vph::make_phantom(dir.path(), o);
    transforms = json::parse(vispack::read_file(dir / "truth/transforms.json"));
    rgb = vispack::read_nrrd(dir / "truth/rgb.nrrd");
    mask = vispack::read_nrrd(dir / "truth/mask.nrrd");
    labels = vispack::read_nrrd(dir / "truth/labels.nrrd");
    W = transforms["width"], H = transforms["height"];
    N = int(transforms["slices"].size());
  }
  cv::Mat truth_mask(int k) const {
    return cv::Mat(H, W, CV_8UC1, const_cast<std::uint8_t*>(mask.as<std::uint8_t>()) + W * H * k);
  }
  cv::Mat truth_labels(int k) const {
    return cv::Mat(H, W, CV_16UC1,
                   const_cast<std::uint16_t*>(labels.as<std::uint16_t>()) + W * H * k);
  }
  cv::Mat truth_rgb(int k) const {
    return cv::Mat(H, W, CV_8UC3,
                   const_cast<std::uint8_t*>(rgb.as<std::uint8_t>()) + std::size_t(W) * H * 3 * k);
  }
  std::string file(const std::string& stem, int k) const {
    char name[64];
    std::snprintf(name, sizeof name, "%s/%s_%04d.png", stem.c_str(), stem.c_str(), k);
    return dir / name;
  }
};

vph::PhantomOptions anatomy_options(std::uint64_t seed = 3) {
  vph::PhantomOptions o;
  o.preset = "anatomy";
  o.seed = seed;
  o.slices = kSlices;
  return o;
}

Folder& anatomy() {
  static Folder f(anatomy_options());
  return f;
}

std::map<std::string, std::string> folder_bytes(const std::string& root) {
  std::map<std::string, std::string> files;
  for (const auto& entry : fs::recursive_directory_iterator(root))
    if (entry.is_regular_file())
      files[fs::relative(entry.path(), root).string()] = vispack::read_file(entry.path().string());
  return files;
}

// Pixels whose label is constant over a (2r+1)² window.
cv::Mat interior(const cv::Mat& labels16, int r) {
  cv::Mat lab, lo, hi;
  labels16.convertTo(lab, CV_32F);
  const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * r + 1, 2 * r + 1));
  cv::erode(lab, lo, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  cv::dilate(lab, hi, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  return lo == hi;
}

// Observed-slice pixels that look like the green fiducial tubes.
int green_pixels(const cv::Mat& rgb) {
  int n = 0;
  for (int y = 0; y < rgb.rows; ++y)
    for (int x = 0; x < rgb.cols; ++x) {
      const auto& p = rgb.at<cv::Vec3b>(y, x);
      n += p[1] > p[0] + 50 && p[1] > p[2] + 50;
    }
  return n;
}

}  // namespace

TEST(Anatomy, SameSeedSameBytesOtherThreadCount) {
  vph::PhantomOptions a = anatomy_options(9), b = anatomy_options(9);
  a.slices = b.slices = 8;
  a.threads = 1, b.threads = 2;
  Folder fa(a), fb(b);
  const auto ba = folder_bytes(fa.dir.path()), bb = folder_bytes(fb.dir.path());
  ASSERT_EQ(ba.size(), bb.size());
  for (const auto& [name, bytes] : ba) {
    ASSERT_TRUE(bb.count(name)) << name;
    EXPECT_TRUE(bytes == bb.at(name)) << name << " differs";
  }
  // Another seed: other drift, other texture.
  Folder fc(anatomy_options(10));
  EXPECT_NE(vispack::read_file(fa.file("rgb", 3)), vispack::read_file(fc.file("rgb", 3)));
}

TEST(Anatomy, OutlineMovesSteadilyAndTapersToNothingAtBothEnds) {
  Folder& f = anatomy();
  ASSERT_EQ(f.N, kSlices);
  std::vector<double> area(std::size_t(f.N)), cx(std::size_t(f.N)), cy(std::size_t(f.N));
  for (int k = 0; k < f.N; ++k) {
    const cv::Moments m = cv::moments(f.truth_mask(k), true);
    area[std::size_t(k)] = m.m00;
    cx[std::size_t(k)] = m.m00 > 0 ? m.m10 / m.m00 : NAN;
    cy[std::size_t(k)] = m.m00 > 0 ? m.m01 / m.m00 : NAN;
  }
  const double max_area = *std::max_element(area.begin(), area.end());
  // Nothing at both ends; small next to them; the body in the middle covers a good part.
  EXPECT_EQ(area.front(), 0);
  EXPECT_EQ(area.back(), 0);
  EXPECT_LT(area[1], 0.5 * max_area);
  EXPECT_LT(area[std::size_t(f.N) - 2], 0.5 * max_area);
  EXPECT_GT(max_area, 0.15 * f.W * f.H);
  // The centroid moves steadily: a straight-line fit over the slices with a body has the slope
  // of the model's shift (0.3 × H/2 over the stack) within 25 %, and every step goes the same
  // way (x increases by 0.3..3 px per slice).
  double sx = 0, sy = 0, sxx = 0, sxy = 0;
  int n = 0;
  for (int k = 1; k + 1 < f.N; ++k) {
    sx += k, sy += cx[std::size_t(k)], sxx += double(k) * k, sxy += k * cx[std::size_t(k)], ++n;
    if (k > 1) {
      const double step = cx[std::size_t(k)] - cx[std::size_t(k) - 1];
      EXPECT_GT(step, 0.3) << "slice " << k;
      EXPECT_LT(step, 3.0) << "slice " << k;
    }
  }
  const double slope = (n * sxy - sx * sy) / (n * sxx - sx * sx);
  const double expected = 0.3 * f.H / 2 / (f.N - 1);
  EXPECT_NEAR(slope, expected, 0.25 * expected);
  EXPECT_GT(cy[std::size_t(f.N) - 2] - cy[1], 0.5 * 0.12 * f.H / 2);  // y moves too
}

TEST(Anatomy, OrgansAppearAndVanish) {
  Folder& f = anatomy();
  auto present = [&](int k) {
    std::set<int> s;
    const cv::Mat l = f.truth_labels(k);
    std::map<int, int> count;
    for (int y = 0; y < l.rows; ++y)
      for (int x = 0; x < l.cols; ++x)
        ++count[l.at<std::uint16_t>(y, x)];
    for (const auto& [id, c] : count)
      if (c >= 20) s.insert(id);
    return s;
  };
  const std::set<int> early = present(f.N / 5), late = present(4 * f.N / 5);
  // Heart (6) early only; liver (7) and kidneys (8) late only (phantom_model: label ids).
  EXPECT_TRUE(early.count(6));
  EXPECT_FALSE(late.count(6));
  EXPECT_FALSE(early.count(7));
  EXPECT_TRUE(late.count(7));
  EXPECT_TRUE(late.count(8));
}

TEST(Anatomy, NoFiducialsUnlessAsked) {
  Folder& f = anatomy();
  EXPECT_EQ(f.transforms["fiducials"], false);
  for (int k = 0; k < f.N; k += 5)
    EXPECT_EQ(green_pixels(vispack::pipeline::read_slice(f.file("rgb", k))), 0) << k;
  // Control: asked for, the tubes are there (so the count above can see them).
  vph::PhantomOptions o = anatomy_options();
  o.slices = 4;
  o.fiducials = true;
  Folder with(o);
  EXPECT_GT(green_pixels(vispack::pipeline::read_slice(with.file("rgb", 1))), 100);
}

TEST(Anatomy, TextureIsFreshEverySlice) {
  // Correlation of the colour's deviation from its label's mean between neighbouring slices,
  // over pixels interior to the same label in both: the anatomy preset draws a new texture every
  // slice (≈ 0); the classic small preset keeps it over several slices (high).
  auto neighbour_correlation = [](const Folder& f, int k) {
    const cv::Mat both = interior(f.truth_labels(k), 2) & interior(f.truth_labels(k + 1), 2) &
                         (f.truth_labels(k) == f.truth_labels(k + 1)) & (f.truth_labels(k) > 0);
    std::vector<double> a, b;
    for (int i : {k, k + 1}) {
      std::map<int, std::pair<double, int>> mean;
      const cv::Mat l = f.truth_labels(i), g = f.truth_rgb(i);
      for (int y = 0; y < f.H; ++y)
        for (int x = 0; x < f.W; ++x)
          if (both.at<std::uint8_t>(y, x)) {
            auto& m = mean[l.at<std::uint16_t>(y, x)];
            m.first += g.at<cv::Vec3b>(y, x)[1], ++m.second;
          }
      auto& out = i == k ? a : b;
      for (int y = 0; y < f.H; ++y)
        for (int x = 0; x < f.W; ++x)
          if (both.at<std::uint8_t>(y, x)) {
            const auto& m = mean[l.at<std::uint16_t>(y, x)];
            out.push_back(g.at<cv::Vec3b>(y, x)[1] - m.first / m.second);
          }
    }
    double sab = 0, saa = 0, sbb = 0;
    for (std::size_t i = 0; i < a.size(); ++i)
      sab += a[i] * b[i], saa += a[i] * a[i], sbb += b[i] * b[i];
    return sab / std::sqrt(saa * sbb);
  };
  Folder& f = anatomy();
  const double fresh = neighbour_correlation(f, f.N / 2);
  vph::PhantomOptions o;
  o.preset = "small";
  o.seed = 3;
  o.slices = 6;
  o.defects = false;
  Folder classic(o);
  const double kept = neighbour_correlation(classic, 2);
  RecordProperty("anatomy_texture_correlation", std::to_string(fresh));
  RecordProperty("small_texture_correlation", std::to_string(kept));
  EXPECT_LT(std::fabs(fresh), 0.3);
  EXPECT_GT(kept, 0.6);
}

TEST(Anatomy, DriftOffIsExactlyZeroWhileAnatomyMoves) {
  vph::PhantomOptions o = anatomy_options();
  o.drift = false;
  o.jump = false;
  Folder f(o);
  const json& s0 = f.transforms["slices"][0];
  EXPECT_GT(std::hypot(double(s0["dx_px"]), double(s0["dy_px"])), 3.0);  // the camera offset
  for (int k = 1; k < f.N; ++k) {
    const json& s = f.transforms["slices"][k];
    EXPECT_EQ(double(s["dx_px"]), double(s0["dx_px"])) << k;
    EXPECT_EQ(double(s["dy_px"]), double(s0["dy_px"])) << k;
    EXPECT_EQ(double(s["rotation_deg"]), double(s0["rotation_deg"])) << k;
    EXPECT_FALSE(s["jump"].get<bool>()) << k;
  }
  // The anatomy still moves: the same centroid shift as with drift.
  const cv::Moments a = cv::moments(f.truth_mask(2), true),
                    b = cv::moments(f.truth_mask(f.N - 3), true);
  EXPECT_GT(b.m10 / b.m00 - a.m10 / a.m00, 0.6 * 0.3 * f.H / 2);
}

TEST(Anatomy, CtIsTwiceCoarserAndConfigCarriesTheFrame) {
  Folder& f = anatomy();
  EXPECT_NEAR(double(f.transforms["ct_to_rgb"]["scale"]), 2.0, 1e-9);
  EXPECT_EQ(f.transforms["frame"], "ct");
  const cv::Mat ct = vispack::pipeline::read_slice(f.file("ct", 0));
  EXPECT_EQ(ct.type(), CV_16UC1);
  // The CT covers at least the colour frame.
  EXPECT_GE(ct.cols * 0.66, f.W * 0.33);
  const json config = json::parse(vispack::read_file(f.dir / "config.json"));
  EXPECT_EQ(config["register"]["output_frame"]["rotation_deg"], 0.0);
  EXPECT_EQ(config["register"]["output_frame"]["dx_px"], 0.0);
  EXPECT_DOUBLE_EQ(double(config["ct"]["pixel_spacing_mm"][0]), 0.66);
  // --ct-scale overrides the preset's CT.
  vph::PhantomOptions o = anatomy_options();
  o.slices = 3;
  o.ct_scale = 3;
  Folder three(o);
  EXPECT_NEAR(double(three.transforms["ct_to_rgb"]["scale"]), 3.0, 1e-9);
}

// Undoing the true transform of an observed slice gives the truth colour (gain divided out)
// within the noise, and the truth mask is where the observed slice shows tissue.
TEST(Anatomy, TruthAgreesWithTheObservedSlices) {
  Folder& f = anatomy();
  const double cx = (f.W - 1) * 0.5, cy = (f.H - 1) * 0.5;
  for (int k = 2; k < f.N - 2; k += 4) {
    const json& s = f.transforms["slices"][k];
    const double th = double(s["rotation_deg"]) * vispack::kPi / 180, c = std::cos(th),
                 n = std::sin(th);
    const double dx = s["dx_px"], dy = s["dy_px"];
    const cv::Mat q_to_p = (cv::Mat_<double>(2, 3) << c, -n, cx - c * cx + n * cy + dx, n, c,
                            cy - n * cx - c * cy + dy);
    const cv::Mat observed = vispack::pipeline::read_slice(f.file("rgb", k));
    cv::Mat registered, truth, diff;
    cv::warpAffine(observed, registered, q_to_p, observed.size(),
                   cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
    registered.convertTo(registered, CV_32FC3, 1.0 / double(s["gain"]));
    f.truth_rgb(k).convertTo(truth, CV_32FC3);
    cv::absdiff(registered, truth, diff);
    cv::Mat grey;
    cv::cvtColor(diff, grey, cv::COLOR_RGB2GRAY);
    const cv::Mat inner = interior(f.truth_labels(k), 2);
    const double mae = cv::mean(grey, inner)[0];
    // Noise σ 3 (mean |N| ≈ 2.4, less after bilinear averaging) plus the texture's interpolation.
    EXPECT_LT(mae, 4.0) << "slice " << k;
    // Control: one pixel off gives a clearly larger error (the texture is fine).
    cv::Mat off = q_to_p.clone(), shifted;
    off.at<double>(0, 2) += 1.0;
    cv::warpAffine(observed, shifted, off, observed.size(),
                   cv::INTER_LINEAR | cv::WARP_INVERSE_MAP);
    shifted.convertTo(shifted, CV_32FC3, 1.0 / double(s["gain"]));
    cv::absdiff(shifted, truth, diff);
    cv::cvtColor(diff, grey, cv::COLOR_RGB2GRAY);
    EXPECT_GT(cv::mean(grey, inner)[0], 1.3 * mae) << "slice " << k;
    // Tissue (red above blue) exactly inside the truth mask, gel (blue above red) outside,
    // away from the outline.
    cv::Mat body_in = interior(f.truth_mask(k), 2) & (f.truth_mask(k) > 0);
    cv::Mat body_out = interior(f.truth_mask(k), 2) & (f.truth_mask(k) == 0);
    int wrong = 0;
    for (int y = 0; y < f.H; ++y)
      for (int x = 0; x < f.W; ++x) {
        const auto& p = registered.at<cv::Vec3f>(y, x);
        if (body_in.at<std::uint8_t>(y, x)) wrong += p[0] <= p[2];
        if (body_out.at<std::uint8_t>(y, x)) wrong += p[2] <= p[0];
      }
    EXPECT_EQ(wrong, 0) << "slice " << k;
  }
}

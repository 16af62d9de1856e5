// Colour slices synthesised from a CT (from_ct.h): on a small synthetic CT volume (always) and on
// the real head CT (data/samples/head-ct; skipped with a message when it has not been fetched).
// Checks determinism, the body model (holder excluded), the CT written as it was, and that the
// truth agrees with the slices: undoing the true transform gives the truth colour within the
// noise, tissue shows exactly inside the truth mask, the seg slices decode to their truth IDs.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <map>
#include <string>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/common/nrrd.h"
#include "vispack/phantom/from_ct.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vph = vispack::phantom;
namespace fs = std::filesystem;
using nlohmann::json;
using vispack::test::TempDir;

namespace {

// A 48×48×8 CT: a soft-tissue ball (40 HU, 1 mm pixels) with a bony shell, growing then
// shrinking along z, in air, and a separate thin plastic ring (300 HU) around it: the holder.
vph::CtVolume synthetic_ct() {
  vph::CtVolume ct;
  ct.width = 48, ct.height = 48, ct.slices = 8;
  ct.spacing_mm = {1.0, 1.0, 2.0};
  ct.source = "synthetic";
  ct.hu.assign(std::size_t(48) * 48 * 8, -1000);
  for (int k = 0; k < 8; ++k) {
    const double r = 9 + 5 * std::sin(vispack::kPi * (k + 0.5) / 8);
    for (int y = 0; y < 48; ++y)
      for (int x = 0; x < 48; ++x) {
        const double d = std::hypot(x - 22.0 - 0.5 * k, y - 24.0);
        std::int16_t& v = ct.hu[(std::size_t(k) * 48 + y) * 48 + x];
        if (d < r - 2)
          v = 40 + std::int16_t((x * 7 + y * 3 + k) % 11);
        else if (d < r)
          v = 700;
        else if (std::fabs(d - 21.5) < 1.0 && y < 30)
          v = 300;
      }
  }
  return ct;
}

struct Folder {
  TempDir dir{"vispack-from-ct"};
  vph::FromCtSummary summary;
  json transforms;
  vispack::NrrdVolume rgb, ct, mask, labels, seg_labels;
  int W = 0, H = 0, N = 0;
  Folder(const vph::CtVolume& volume, vph::FromCtOptions o) {
    o.quiet = true;
    summary = vph::make_phantom_from_ct(dir.path(), volume, o);
    transforms = json::parse(vispack::read_file(dir / "truth/transforms.json"));
    rgb = vispack::read_nrrd(dir / "truth/rgb.nrrd");
    ct = vispack::read_nrrd(dir / "truth/ct.nrrd");
    mask = vispack::read_nrrd(dir / "truth/mask.nrrd");
    labels = vispack::read_nrrd(dir / "truth/labels.nrrd");
    seg_labels = vispack::read_nrrd(dir / "truth/seg_labels.nrrd");
    W = transforms["width"], H = transforms["height"], N = int(transforms["slices"].size());
  }
  template <class T>
  cv::Mat plane(const vispack::NrrdVolume& v, int type, int k, int channels = 1) const {
    return cv::Mat(H, W, type,
                   const_cast<T*>(v.as<T>()) + std::size_t(W) * H * channels * std::size_t(k));
  }
  std::string file(const std::string& stem, int k) const {
    char name[64];
    std::snprintf(name, sizeof name, "%s/%s_%04d.png", stem.c_str(), stem.c_str(), k);
    return dir / name;
  }
};

std::map<std::string, std::string> folder_bytes(const std::string& root) {
  std::map<std::string, std::string> files;
  for (const auto& entry : fs::recursive_directory_iterator(root))
    if (entry.is_regular_file())
      files[fs::relative(entry.path(), root).string()] = vispack::read_file(entry.path().string());
  return files;
}

cv::Mat interior(const cv::Mat& labels, int r) {
  cv::Mat lab, lo, hi;
  labels.convertTo(lab, CV_32F);
  const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * r + 1, 2 * r + 1));
  cv::erode(lab, lo, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  cv::dilate(lab, hi, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  return lo == hi;
}

// The truth agrees with what was written, slice by slice (every `step`-th slice).
void check_truth_against_slices(const Folder& f, int step) {
  const double cx = (f.W - 1) * 0.5, cy = (f.H - 1) * 0.5;
  const json palette = json::parse(vispack::read_file(f.dir / "palette.json"));
  std::map<std::uint32_t, int> id_of{{0, 0}};
  for (const auto& l : palette["labels"])
    id_of[(std::uint32_t(l["colour"][0]) << 16) | (std::uint32_t(l["colour"][1]) << 8) |
          std::uint32_t(l["colour"][2])] = l["id"];
  for (int k = 0; k < f.N; k += step) {
    SCOPED_TRACE("slice " + std::to_string(k));
    const json& s = f.transforms["slices"][k];
    const double th = double(s["rotation_deg"]) * vispack::kPi / 180, c = std::cos(th),
                 n = std::sin(th);
    const double dx = s["dx_px"], dy = s["dy_px"];
    const cv::Mat q_to_p = (cv::Mat_<double>(2, 3) << c, -n, cx - c * cx + n * cy + dx, n, c,
                            cy - n * cx - c * cy + dy);
    // Divide the lighting out on the observed grid, then undo the transform.
    cv::Mat observed;
    vispack::pipeline::read_slice(f.file("rgb", k)).convertTo(observed, CV_32FC3);
    const double gain = s["gain"], tx = s["light_tilt"][0], ty = s["light_tilt"][1];
    for (int y = 0; y < f.H; ++y)
      for (int x = 0; x < f.W; ++x)
        observed.at<cv::Vec3f>(y, x) /= float(gain * (1 + tx * (x - cx) + ty * (y - cy)));
    cv::Mat registered, truth, diff, grey;
    cv::warpAffine(observed, registered, q_to_p, observed.size(),
                   cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
    f.plane<std::uint8_t>(f.rgb, CV_8UC3, k, 3).convertTo(truth, CV_32FC3);
    const cv::Mat truth_labels = f.plane<std::uint16_t>(f.labels, CV_16UC1, k);
    const cv::Mat truth_mask = f.plane<std::uint8_t>(f.mask, CV_8UC1, k);
    const cv::Mat inner = interior(truth_labels, 2);
    cv::absdiff(registered, truth, diff);
    cv::cvtColor(diff, grey, cv::COLOR_RGB2GRAY);
    const double mae = cv::mean(grey, inner)[0];
    EXPECT_LT(mae, 4.5);  // noise σ 3 (8 bit) plus interpolation of the texture
    // Control on a band of ±3 px around the body outline: one pixel off is clearly worse.
    cv::Mat band, inside;
    const cv::Mat k7 = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(7, 7));
    cv::dilate(truth_mask, band, k7);
    cv::erode(truth_mask, inside, k7);
    band = (band - inside) > 0;
    const double band_mae = cv::mean(grey, band)[0];
    cv::Mat off = q_to_p.clone(), shifted;
    off.at<double>(1, 2) += 1.0;
    cv::warpAffine(observed, shifted, off, observed.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                   cv::BORDER_REPLICATE);
    cv::absdiff(shifted, truth, diff);
    cv::cvtColor(diff, grey, cv::COLOR_RGB2GRAY);
    EXPECT_GT(cv::mean(grey, band)[0], 1.5 * band_mae) << "band MAE " << band_mae;
    // Tissue (red above blue) inside the truth mask, gel (blue above red) outside, away from
    // the outline: the colour shows the body exactly where the mask says.
    // Exactly in the truth colour (no noise); in the registered observed slice up to the odd
    // pixel where the sensor noise flips a pale tissue.
    // Tissue is where the truth labels are non-zero: the truth mask also counts enclosed
    // cavities (gel-filled in the colour) as body, and must contain every tissue pixel.
    const cv::Mat tissue = truth_labels > 0;
    EXPECT_EQ(cv::countNonZero(tissue & (truth_mask == 0)), 0);
    const cv::Mat away = interior(tissue, 2);
    int wrong = 0, wrong_truth = 0, counted = 0;
    for (int y = 0; y < f.H; ++y)
      for (int x = 0; x < f.W; ++x) {
        const bool body = tissue.at<std::uint8_t>(y, x);
        const auto& t = truth.at<cv::Vec3f>(y, x);
        wrong_truth += body ? t[0] <= t[2] : t[2] <= t[0];
        if (!away.at<std::uint8_t>(y, x)) continue;
        const auto& p = registered.at<cv::Vec3f>(y, x);
        ++counted;
        wrong += body ? p[0] <= p[2] : p[2] <= p[0];
      }
    EXPECT_EQ(wrong_truth, 0);
    EXPECT_LE(wrong, 1e-4 * counted) << "of " << counted;
    // The seg slice decodes (palette, exact PNG) to truth/seg_labels.nrrd, and under the true
    // transform to the truth labels away from class edges.
    const cv::Mat seg = vispack::pipeline::read_slice(f.file("seg", k));
    const cv::Mat seg_ids = f.plane<std::uint16_t>(f.seg_labels, CV_16UC1, k);
    int mismatched = 0;
    for (int y = 0; y < f.H; ++y)
      for (int x = 0; x < f.W; ++x) {
        const auto& p = seg.at<cv::Vec3b>(y, x);
        const std::uint32_t key = (std::uint32_t(p[0]) << 16) | (std::uint32_t(p[1]) << 8) | p[2];
        const bool bad = !id_of.count(key) || id_of[key] != seg_ids.at<std::uint16_t>(y, x);
        if (bad && mismatched < 3)
          ADD_FAILURE() << "seg " << x << "," << y << " colour " << int(p[0]) << " " << int(p[1])
                        << " " << int(p[2]) << " truth id " << seg_ids.at<std::uint16_t>(y, x);
        mismatched += bad;
      }
    EXPECT_EQ(mismatched, 0);
    cv::Mat seg_registered;
    cv::warpAffine(seg_ids, seg_registered, q_to_p, seg_ids.size(),
                   cv::INTER_NEAREST | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
    const cv::Mat differs = (seg_registered != truth_labels) & inner & (truth_labels > 0);
    EXPECT_LE(cv::countNonZero(differs), 0.002 * cv::countNonZero(inner & (truth_labels > 0)));
    // The body stays inside the observed frame: its 2-pixel border is gel.
    for (int y = 0; y < f.H; ++y)
      for (int x = 0; x < f.W; ++x) {
        if (x < 2 || y < 2 || x >= f.W - 2 || y >= f.H - 2) {
          ASSERT_EQ(seg_ids.at<std::uint16_t>(y, x), 0) << x << "," << y;
        }
      }
  }
}

// The written CT is the source CT, drift-free, stored = HU + 1024.
void check_ct_written(const Folder& f, const vph::CtVolume& ct, int first) {
  for (int k = 0; k < f.N; k += 2) {
    const cv::Mat stored = vispack::pipeline::read_slice(f.file("ct", k));
    ASSERT_EQ(stored.type(), CV_16UC1);
    ASSERT_EQ(stored.cols, ct.width);
    int differ = 0;
    for (int y = 0; y < ct.height; ++y)
      for (int x = 0; x < ct.width; ++x)
        differ += int(stored.at<std::uint16_t>(y, x)) - 1024 !=
                  ct.slice(first + k)[std::size_t(y) * ct.width + x];
    EXPECT_EQ(differ, 0) << "slice " << k;
  }
}

bool head_ct_present(std::string* dir) {
  const char* env = std::getenv("VISPACK_SAMPLES_DIR");
  *dir = (env && *env ? std::string(env) : std::string(VISPACK_SOURCE_DIR) + "/data/samples") +
         "/head-ct";
  return fs::exists(*dir + "/.stamp");
}

}  // namespace

TEST(FromCt, SyntheticSameBytesWhateverTheThreads) {
  const vph::CtVolume ct = synthetic_ct();
  vph::FromCtOptions a, b;
  a.seed = b.seed = 4;
  a.threads = 1, b.threads = 2;
  Folder fa(ct, a), fb(ct, b);
  const auto ba = folder_bytes(fa.dir.path()), bb = folder_bytes(fb.dir.path());
  ASSERT_EQ(ba.size(), bb.size());
  for (const auto& [name, bytes] : ba)
    EXPECT_TRUE(bytes == bb.at(name)) << name;
  vph::FromCtOptions c = a;
  c.seed = 5;
  Folder fc(ct, c);
  EXPECT_NE(vispack::read_file(fa.file("rgb", 2)), vispack::read_file(fc.file("rgb", 2)));
}

TEST(FromCt, SyntheticGridFrameBodyAndTruth) {
  const vph::CtVolume ct = synthetic_ct();
  vph::FromCtOptions o;
  o.seed = 2;
  Folder f(ct, o);
  // 2× the CT plus 64 px of gel each side; the CT frame at the colour resolution.
  EXPECT_EQ(f.W, 48 * 2 + 128);
  EXPECT_EQ(f.N, 8);
  EXPECT_DOUBLE_EQ(f.rgb.spacing_mm[0], 0.5);
  EXPECT_DOUBLE_EQ(f.rgb.spacing_mm[2], 2.0);
  EXPECT_EQ(f.transforms["frame"], "ct");
  EXPECT_TRUE(f.transforms["reference_slice"].is_null());
  EXPECT_EQ(double(f.transforms["ct_to_rgb"]["scale"]), 2.0);
  EXPECT_EQ(double(f.transforms["ct_to_rgb"]["rotation_deg"]), 0.0);
  const json& s0 = f.transforms["slices"][0];
  EXPECT_GT(std::hypot(double(s0["dx_px"]), double(s0["dy_px"])), 4.0);  // camera offset
  EXPECT_GT(std::fabs(double(s0["rotation_deg"])), 0.5);
  int jumps = 0;
  for (int k = 1; k < f.N; ++k) {
    const json &s = f.transforms["slices"][k], &p = f.transforms["slices"][k - 1];
    const double move = std::hypot(double(s["dx_px"]) - double(p["dx_px"]),
                                   double(s["dy_px"]) - double(p["dy_px"]));
    if (s["jump"]) {
      ++jumps;
      EXPECT_EQ(k, f.N / 2);
      EXPECT_GT(move, 10.0);
      EXPECT_GT(std::fabs(double(s["rotation_deg"]) - double(p["rotation_deg"])), 2.5);
    } else {
      EXPECT_LT(move, 2.0) << k;
    }
  }
  EXPECT_EQ(jumps, 1);
  // The body: the ball, never the holder ring (a separate component), and only above −400 HU.
  // CT pixel u lands on q = c + 2 (u − c_ct): u = (22 + 0.5k, 24) is the ball's centre.
  for (int k = 0; k < f.N; ++k) {
    const cv::Mat m = f.plane<std::uint8_t>(f.mask, CV_8UC1, k);
    const cv::Mat hu = f.plane<std::int16_t>(f.ct, CV_16SC1, k);
    const int qx = int(std::lround(111.5 + 2 * (22 + 0.5 * k - 23.5))),
              qy = int(std::lround(111.5 + 2 * (24 - 23.5)));
    EXPECT_EQ(m.at<std::uint8_t>(qy, qx), 1) << k;
    int holder = 0, below = 0;
    for (int y = 0; y < f.H; ++y)
      for (int x = 0; x < f.W; ++x) {
        holder += hu.at<std::int16_t>(y, x) > 100 && !m.at<std::uint8_t>(y, x);
        below += m.at<std::uint8_t>(y, x) && hu.at<std::int16_t>(y, x) < -400;
      }
    EXPECT_GT(holder, 100) << k;  // the ring is in the CT, not in the body
    EXPECT_EQ(below, 0) << k;
  }
  check_ct_written(f, ct, 0);
  check_truth_against_slices(f, 1);
  // The config reads back, with the CT section and the output frame.
  const vispack::pipeline::Config config = vispack::pipeline::load_config(f.dir / "config.json");
  ASSERT_TRUE(config.ct.has_value());
  EXPECT_DOUBLE_EQ(config.ct->pixel_spacing_mm[0], 1.0);
  EXPECT_DOUBLE_EQ(config.spacing_mm[0], 0.5);
  EXPECT_EQ(config.registration.output_frame.rotation_deg, 0.0);
}

TEST(FromCt, ReadsNrrdAndRejectsWhatIsNot) {
  TempDir dir("vispack-from-ct-read");
  const vph::CtVolume ct = synthetic_ct();
  vispack::NrrdVolume v;
  v.type = vispack::NrrdType::kInt16;
  v.dims = {ct.width, ct.height, ct.slices};
  v.spacing_mm = ct.spacing_mm;
  v.data.resize(v.byte_size());
  std::memcpy(v.data.data(), ct.hu.data(), v.data.size());
  vispack::write_nrrd(dir / "ct.nrrd", v);
  const vph::CtVolume back = vph::read_ct_volume(dir / "ct.nrrd");
  EXPECT_EQ(back.width, 48);
  EXPECT_EQ(back.slices, 8);
  EXPECT_DOUBLE_EQ(back.spacing_mm[2], 2.0);
  EXPECT_EQ(back.hu, ct.hu);
  vispack::write_file_atomic(dir / "x.txt", "hello");
  EXPECT_THROW(vph::read_ct_volume(dir / "x.txt"), vispack::InputError);
  EXPECT_THROW(vph::read_ct_volume(dir / "absent.nrrd"), vispack::IoError);
  EXPECT_THROW(vph::read_ct_volume(dir.path()), vispack::InputError);  // no config.json
  vph::FromCtOptions o;
  o.slices = 9;  // more than the CT has
  EXPECT_THROW(vph::make_phantom_from_ct(dir / "out", ct, o), vispack::UsageError);
}

TEST(FromCt, RealHeadCt) {
  std::string sample;
  if (!head_ct_present(&sample))
    GTEST_SKIP() << "head-ct sample not found in " << sample
                 << " (run scripts/fetch-sample-data.sh head-ct)";
  const vph::CtVolume ct = vph::read_ct_volume(sample);
  ASSERT_EQ(ct.width, 256);
  ASSERT_EQ(ct.slices, 108);
  EXPECT_NEAR(ct.spacing_mm[0], 0.9570312, 1e-7);
  vph::FromCtOptions o;
  o.seed = 1;
  o.slices = 6;
  o.first = 40;
  Folder f(ct, o);
  EXPECT_EQ(f.W, 640);
  EXPECT_NEAR(f.rgb.spacing_mm[0], 0.9570312 / 2, 1e-7);
  EXPECT_GT(f.summary.body_fraction, 0.15);
  // The head holder (HU 100..600, a separate arc) is in the CT but never in the body mask.
  for (int k = 0; k < f.N; ++k) {
    const cv::Mat m = f.plane<std::uint8_t>(f.mask, CV_8UC1, k);
    const cv::Mat hu = f.plane<std::int16_t>(f.ct, CV_16SC1, k);
    EXPECT_GT(cv::countNonZero((hu > 100) & (m == 0)), 300) << k;
  }
  check_ct_written(f, ct, 40);
  check_truth_against_slices(f, 2);
}

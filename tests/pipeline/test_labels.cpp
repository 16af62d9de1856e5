// vispack-labels: palette matching (exact, nearest within tolerance, big palettes, IDs up to
// 65535), strict mode, id maps, nearest-neighbour resampling, and the stage against the
// phantom's truth (true transforms, JPEG segmentation, and end to end through registration).
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <random>

#include <opencv2/imgproc.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/nrrd.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/labels/labels.h"
#include "vispack/pipeline/labels/labels_stage.h"
#include "vispack/pipeline/register/register.h"
#include "vispack/pipeline/register/register_stage.h"

using namespace vispack;
using namespace vispack::pipeline;
using namespace vispack::phantom;
using vispack::test::TempDir;
namespace fs = std::filesystem;

namespace {

std::vector<PaletteEntry> random_palette(int n, unsigned seed) {
  std::mt19937 rng(seed);
  std::vector<PaletteEntry> out;
  std::set<std::uint32_t> used_colours, used_ids;
  while (int(out.size()) < n) {
    PaletteEntry e;
    e.id = std::uint16_t(1 + rng() % 65535);
    if (out.empty()) e.id = 65535;  // the largest ID must work
    e.colour = {std::uint8_t(rng()), std::uint8_t(rng()), std::uint8_t(rng())};
    std::uint32_t key = (e.colour[0] << 16) | (e.colour[1] << 8) | e.colour[2];
    if (key == 0 || !used_colours.insert(key).second || !used_ids.insert(e.id).second) continue;
    e.name = "s" + std::to_string(e.id);
    out.push_back(e);
  }
  return out;
}

// Brute-force nearest palette colour (ties to the smaller ID, like ColourMatcher).
std::pair<std::uint16_t, double> brute_nearest(const std::vector<PaletteEntry>& p, int r, int g,
                                               int b) {
  int best = 1 << 30;
  std::uint16_t id = 0;
  auto consider = [&](int cr, int cg, int cb, std::uint16_t cid) {
    int d = (cr - r) * (cr - r) + (cg - g) * (cg - g) + (cb - b) * (cb - b);
    if (d < best || (d == best && cid < id)) best = d, id = cid;
  };
  for (const auto& e : p)
    consider(e.colour[0], e.colour[1], e.colour[2], e.id);
  consider(0, 0, 0, 0);  // the implicit background
  return {id, std::sqrt(double(best))};
}

NrrdVolume read_truth(const std::string& dir, const std::string& name) {
  return read_nrrd(dir + "/truth/" + name);
}

struct Agreement {
  std::uint64_t equal = 0, total = 0;
  std::uint64_t interior_wrong = 0,
                interior = 0;              // pixels whose truth 3x3 neighbourhood is uniform
  std::uint64_t body_equal = 0, body = 0;  // inside truth/mask.nrrd
  double fraction() const { return total ? double(equal) / total : 0; }
  double body_fraction() const { return body ? double(body_equal) / body : 0; }
};

// Compares work/labels/labels_NNNN.png (or `slices`) with truth/labels.nrrd. Skips the black
// and the duplicated slice of a phantom with defects: their seg file shows nothing, or the
// previous slice's anatomy, so no labels stage can recover truth there.
Agreement compare_with_truth(const std::string& phantom, const std::vector<cv::Mat>& slices) {
  NrrdVolume truth = read_truth(phantom, "labels.nrrd");
  NrrdVolume mask = read_truth(phantom, "mask.nrrd");
  const StackTransforms truth_t = read_transforms(phantom + "/truth/transforms.json");
  const int nx = int(truth.dims[0]), ny = int(truth.dims[1]), nz = int(truth.dims[2]);
  EXPECT_EQ(int(slices.size()), nz);
  const std::uint16_t* t = truth.as<std::uint16_t>();
  const std::uint8_t* m = mask.as<std::uint8_t>();
  Agreement a;
  for (int z = 0; z < nz && z < int(slices.size()); ++z) {
    if (truth_t.slices[z].black || truth_t.slices[z].duplicate_of) continue;
    const cv::Mat& s = slices[z];
    EXPECT_EQ(s.cols, nx);
    EXPECT_EQ(s.rows, ny);
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x) {
        std::size_t i = (std::size_t(z) * ny + y) * nx + x;
        bool eq = s.at<std::uint16_t>(y, x) == t[i];
        a.total++;
        a.equal += eq;
        if (m[i]) {
          a.body++;
          a.body_equal += eq;
        }
        bool uniform = x > 0 && y > 0 && x < nx - 1 && y < ny - 1;
        for (int dy = -1; uniform && dy <= 1; ++dy)
          for (int dx = -1; dx <= 1; ++dx)
            if (t[(std::size_t(z) * ny + y + dy) * nx + x + dx] != t[i]) uniform = false;
        if (uniform) {
          a.interior++;
          a.interior_wrong += !eq;
        }
      }
  }
  return a;
}

std::vector<cv::Mat> read_label_slices(const Config& config, int n) {
  std::vector<cv::Mat> out;
  for (int k = 0; k < n; ++k)
    out.push_back(read_slice(labels_path(config, k)));
  return out;
}

}  // namespace

TEST(Palette, ReadsAndRejectsBadEntries) {
  TempDir dir;
  write_file_atomic(dir / "p.json", R"({"labels":[{"id":1,"name":"skin","colour":[230,180,140]},
                                                  {"id":65535,"name":"last","colour":[1,2,3]}]})");
  auto p = read_palette(dir / "p.json");
  ASSERT_EQ(p.size(), 2u);
  EXPECT_EQ(p[1].id, 65535);
  EXPECT_EQ(p[0].colour[1], 180);
  write_file_atomic(dir / "dup.json",
                    R"({"labels":[{"id":1,"colour":[1,2,3]},{"id":2,"colour":[1,2,3]}]})");
  try {
    read_palette(dir / "dup.json");
    FAIL() << "duplicate colour accepted";
  } catch (const FormatError& e) {
    EXPECT_NE(std::string(e.what()).find("labels[1]"), std::string::npos) << e.what();
  }
  write_file_atomic(dir / "big.json", R"({"labels":[{"id":65536,"colour":[1,2,3]}]})");
  EXPECT_THROW(read_palette(dir / "big.json"), FormatError);
}

TEST(ColourMatcher, ExactNearestAndTolerance) {
  std::vector<PaletteEntry> p = {
      {1, "red", {200, 0, 0}}, {2, "green", {0, 200, 0}}, {300, "blue", {0, 0, 200}}};
  ColourMatcher m(p, 24.0);
  auto e = m.match(0, 0, 200);
  EXPECT_TRUE(e.exact);
  EXPECT_EQ(e.id, 300);
  auto n = m.match(190, 10, 5);  // distance sqrt(100 + 100 + 25) = 15 from red
  EXPECT_FALSE(n.exact);
  EXPECT_TRUE(n.matched);
  EXPECT_EQ(n.id, 1);
  EXPECT_NEAR(n.distance, 15.0, 1e-12);
  auto bg = m.match(5, 5, 5);  // near the implicit black background
  EXPECT_TRUE(bg.matched);
  EXPECT_EQ(bg.id, 0);
  auto far = m.match(100, 100, 100);  // ~141 from every palette colour
  EXPECT_FALSE(far.matched);
  EXPECT_EQ(far.id, 0);
}

// 2,000 random colours with IDs up to 65,535: the k-d tree agrees with brute force on every
// query, and mapping a noisy 1024x1024 slice stays fast.
TEST(ColourMatcher, LargePaletteAgreesWithBruteForce) {
  auto palette = random_palette(2000, 11);
  const double tolerance = 24.0;
  ColourMatcher m(palette, tolerance);
  std::mt19937 rng(5);
  for (int i = 0; i < 20000; ++i) {
    int r = rng() % 256, g = rng() % 256, b = rng() % 256;
    auto [id, d] = brute_nearest(palette, r, g, b);
    auto got = m.match(std::uint8_t(r), std::uint8_t(g), std::uint8_t(b));
    ASSERT_NEAR(got.distance, d, 1e-9) << r << "," << g << "," << b;
    ASSERT_EQ(got.matched, d <= tolerance);
    if (got.matched) {
      ASSERT_EQ(got.id, id) << r << "," << g << "," << b;
    }
  }
  // A slice of palette colours with +-3 noise per channel (all within tolerance 24 since the
  // noise is at most sqrt(27) ~ 5.2 from the drawn colour, and the drawn colour is the nearest
  // unless another palette colour is closer, which brute force decides).
  cv::Mat slice(1024, 1024, CV_8UC3), expected(1024, 1024, CV_16UC1);
  for (int y = 0; y < slice.rows; ++y)
    for (int x = 0; x < slice.cols; ++x) {
      const auto& e = palette[((y / 16) * 64 + x / 16) % palette.size()];
      cv::Vec3b c;
      for (int k = 0; k < 3; ++k)
        c[k] = cv::saturate_cast<std::uint8_t>(int(e.colour[k]) + int(rng() % 7) - 3);
      slice.at<cv::Vec3b>(y, x) = c;
    }
  LabelStats stats;
  cv::Mat ids = map_colours(slice, m, false, "noisy", &stats);
  for (int y = 0; y < slice.rows; y += 7)
    for (int x = 0; x < slice.cols; x += 5) {
      cv::Vec3b c = slice.at<cv::Vec3b>(y, x);
      ASSERT_EQ(ids.at<std::uint16_t>(y, x), brute_nearest(palette, c[0], c[1], c[2]).first);
    }
  EXPECT_EQ(stats.unmatched, 0u);
  EXPECT_EQ(stats.exact + stats.nearest, std::uint64_t(slice.total()));
  // Its speed is a benchmark's business, not this test's (the labels row of the per-stage table,
  // docs/BENCHMARKS.md "Each stage on one and two cores").
}

TEST(ColourMatcher, StrictModeNamesFileAndPixel) {
  std::vector<PaletteEntry> p = {{1, "red", {200, 0, 0}}};
  ColourMatcher m(p, 10.0);
  cv::Mat slice(4, 5, CV_8UC3, cv::Scalar(200, 0, 0));
  slice.at<cv::Vec3b>(2, 3) = {100, 100, 100};
  LabelStats stats;
  cv::Mat ids = map_colours(slice, m, false, "seg_0007.png", &stats);
  EXPECT_EQ(stats.unmatched, 1u);
  ASSERT_EQ(stats.first_unmatched.size(), 1u);
  EXPECT_EQ(stats.first_unmatched[0].x, 3);
  EXPECT_EQ(stats.first_unmatched[0].y, 2);
  EXPECT_EQ(ids.at<std::uint16_t>(2, 3), 1);  // filled from its matched neighbours (all red)
  EXPECT_EQ(ids.at<std::uint16_t>(0, 0), 1);
  try {
    map_colours(slice, m, true, "seg_0007.png", nullptr);
    FAIL() << "strict mode accepted an unknown colour";
  } catch (const InputError& e) {
    std::string what = e.what();
    EXPECT_NE(what.find("seg_0007.png"), std::string::npos) << what;
    EXPECT_NE(what.find("(3, 2)"), std::string::npos) << what;
  }
}

TEST(Labels, IdModeWithMap) {
  cv::Mat seg(2, 3, CV_16UC1);
  seg.at<std::uint16_t>(0, 0) = 0;
  seg.at<std::uint16_t>(0, 1) = 7;
  seg.at<std::uint16_t>(0, 2) = 65535;
  seg.at<std::uint16_t>(1, 0) = 7;
  seg.at<std::uint16_t>(1, 1) = 9;  // not in the map
  seg.at<std::uint16_t>(1, 2) = 0;
  std::unordered_map<std::uint32_t, std::uint16_t> map = {{7, 70}, {65535, 1}};
  LabelStats stats;
  cv::Mat out = map_ids(seg, &map, false, "ids.png", &stats);
  EXPECT_EQ(out.at<std::uint16_t>(0, 1), 70);
  EXPECT_EQ(out.at<std::uint16_t>(0, 2), 1);
  EXPECT_EQ(out.at<std::uint16_t>(1, 1), 0);
  EXPECT_EQ(stats.unmatched, 1u);
  EXPECT_THROW(map_ids(seg, &map, true, "ids.png", nullptr), InputError);
  cv::Mat same = map_ids(seg, nullptr, true, "ids.png", nullptr);
  EXPECT_EQ(cv::countNonZero(same != seg), 0);
}

// Nearest-neighbour resampling never invents an ID: every output value occurs in the input.
TEST(Labels, ResamplingNeverBlends) {
  cv::Mat in(40, 50, CV_16UC1, cv::Scalar(0));
  in(cv::Rect(0, 0, 25, 40)) = 1;
  in(cv::Rect(25, 0, 25, 40)) = 3;
  SliceTransform t;
  t.rigid.dx_px = 0.5;
  t.rigid.dy_px = -0.37;
  t.rigid.rotation_deg = 3.3;
  cv::Mat out = resample_labels_nearest(in, t, {24.5, 19.5}, in.size());
  int ones = 0, threes = 0;
  for (int y = 0; y < out.rows; ++y)
    for (int x = 0; x < out.cols; ++x) {
      auto v = out.at<std::uint16_t>(y, x);
      ASSERT_TRUE(v == 0 || v == 1 || v == 3) << v;
      ones += v == 1;
      threes += v == 3;
    }
  EXPECT_GT(ones, 800);
  EXPECT_GT(threes, 800);
  // The identity transform returns the input unchanged.
  cv::Mat same = resample_labels_nearest(in, SliceTransform{}, {24.5, 19.5}, in.size());
  EXPECT_EQ(cv::countNonZero(same != in), 0);
}

// The transform convention (docs/ARCHITECTURE.md): observed(p) = truth(q) with
// q = c + R(-θ)(p - c - d); resampling back with the same (θ, d) recovers truth away from edges.
TEST(Labels, ResamplingInvertsTheDrift) {
  const int W = 120, H = 90;
  cv::Mat truth(H, W, CV_16UC1, cv::Scalar(0));
  cv::rectangle(truth, cv::Rect(20, 15, 60, 40), cv::Scalar(5), -1);
  cv::rectangle(truth, cv::Rect(50, 30, 40, 40), cv::Scalar(9), -1);
  SliceTransform t;
  t.rigid.rotation_deg = -3.9;
  t.rigid.dx_px = -5.9;
  t.rigid.dy_px = 3.5;
  const double cx = (W - 1) / 2.0, cy = (H - 1) / 2.0, th = t.rigid.rotation_deg * M_PI / 180.0;
  cv::Mat observed(H, W, CV_16UC1, cv::Scalar(0));
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) {
      double px = x - cx - t.rigid.dx_px, py = y - cy - t.rigid.dy_px;
      double qx = cx + std::cos(th) * px + std::sin(th) * py,
             qy = cy - std::sin(th) * px + std::cos(th) * py;
      int ix = int(std::lround(qx)), iy = int(std::lround(qy));
      if (ix >= 0 && iy >= 0 && ix < W && iy < H)
        observed.at<std::uint16_t>(y, x) = truth.at<std::uint16_t>(iy, ix);
    }
  cv::Mat back = resample_labels_nearest(observed, t, {cx, cy}, truth.size());
  int wrong = 0;
  for (int y = 1; y < H - 1; ++y)
    for (int x = 1; x < W - 1; ++x) {
      cv::Mat n = truth(cv::Rect(x - 1, y - 1, 3, 3));
      double lo, hi;
      cv::minMaxLoc(n, &lo, &hi);
      if (lo == hi) wrong += back.at<std::uint16_t>(y, x) != truth.at<std::uint16_t>(y, x);
    }
  EXPECT_EQ(wrong, 0);  // two nearest-neighbour steps move a sample by < 1.42 px: interior exact
}

// The mapping + resampling against truth with the TRUE transforms (truth/transforms.json copied
// to work/register/transforms.json), so registration error plays no part.
// Why not bit-exact: the phantom draws seg(p) = label(q(p)) at the observed pixel centres p;
// resampling back takes seg at round(p(q)), i.e. the label of a model point up to sqrt(2)/2 px
// from q. So only pixels within 0.71 px of a boundary can differ. Asserted: zero errors at
// pixels whose truth 3x3 neighbourhood is one label, bar thin structures (a 1-px sliver between
// samples: measured 2 of 108,235 such pixels; asserted <= 10), and >= 96 % equal overall
// (boundary pixels are many in the tiny 96x64 phantom; measured 97.5 %).
TEST(LabelsStage, PngSegWithTrueTransformsMatchesTruth) {
  TempDir dir;
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 3;
  po.quiet = true;
  make_phantom(dir.path(), po);
  Config config = load_config(dir / "config.json");
  make_directories(config.work_dir + "/register");
  fs::copy_file(dir / "truth/transforms.json", transforms_path(config));
  StageOptions options;
  options.quiet = true;
  StageResult r = run_labels_stage(config, options);
  EXPECT_EQ(r.processed, 24);
  Agreement a = compare_with_truth(dir.path(), read_label_slices(config, 24));
  std::printf(
      "PNG seg, true transforms: %.4f %% equal, %.4f %% in body, %llu/%llu interior wrong\n",
      100 * a.fraction(), 100 * a.body_fraction(), (unsigned long long)a.interior_wrong,
      (unsigned long long)a.interior);
  EXPECT_LE(a.interior_wrong, 10u);
  EXPECT_GT(a.interior, a.total / 2);
  EXPECT_GE(a.fraction(), 0.96);
  auto report = nlohmann::json::parse(read_file(config.work_dir + "/labels/report.json"));
  EXPECT_EQ(report["quality"]["pixels_unmatched"], 0);  // PNG seg: every colour is exact
  EXPECT_EQ(report["quality"]["pixels_nearest"], 0);

  // A second run finds everything up to date; deleting one output redoes just that slice.
  EXPECT_EQ(run_labels_stage(config, options).processed, 0);
  fs::remove(labels_path(config, 5));
  StageResult again = run_labels_stage(config, options);
  EXPECT_EQ(again.processed, 1);
  EXPECT_EQ(again.skipped, 23);
}

// ---- Against the phantom's truth on the `small` preset (256x192x64, seed 3) ----
//
// Two phantoms generated once for the suite (about a second each): one with PNG segmentation,
// one with JPEG (quality 90) segmentation of the same anatomy and drift. truth/seg_labels.nrrd
// holds the ID of every seg pixel as drawn (on the drifted grid), so the colour -> ID mapping is
// checked on its own, before any resampling.
namespace {
struct SmallPhantom {
  TempDir dir{"vispack-labels-truth"};
  Config config;
  NrrdVolume seg_labels, labels, mask;
  StackTransforms transforms;
  int nx = 0, ny = 0, nz = 0;

  explicit SmallPhantom(bool jpeg) {
    PhantomOptions po;
    po.preset = "small";
    po.seed = 3;
    po.quiet = true;
    po.seg_jpeg = jpeg;
    make_phantom(dir.path(), po);
    config = load_config(dir / "config.json");
    seg_labels = read_truth(dir.path(), "seg_labels.nrrd");
    labels = read_truth(dir.path(), "labels.nrrd");
    mask = read_truth(dir.path(), "mask.nrrd");
    transforms = read_transforms(dir / "truth/transforms.json");
    nx = int(labels.dims[0]), ny = int(labels.dims[1]), nz = int(labels.dims[2]);
  }
  // Slice k of a uint16 truth volume (a view into the volume).
  cv::Mat slice16(NrrdVolume& v, int k) const {
    return cv::Mat(ny, nx, CV_16UC1, v.as<std::uint16_t>() + std::size_t(nx) * ny * k);
  }
  // The seg file of slice k (the phantom numbers its slices 0..N-1).
  std::string seg_file(int k) const { return list_slices(*config.seg).at(std::size_t(k)).path; }
  // The labels stage with the TRUE transforms (registration error plays no part).
  void run_stage_with_true_transforms() {
    make_directories(config.work_dir + "/register");
    fs::copy_file(dir / "truth/transforms.json", transforms_path(config),
                  fs::copy_options::overwrite_existing);
    StageOptions options;
    options.quiet = true;
    run_labels_stage(config, options);
  }
};

SmallPhantom& small_png() {
  static SmallPhantom p(false);
  return p;
}
SmallPhantom& small_jpeg() {
  static SmallPhantom p(true);
  return p;
}
}  // namespace

// The seg files the phantom wrote show exactly the IDs of truth/seg_labels.nrrd: with PNG
// segmentation the mapping is exact on every pixel of every slice (black slice included), and
// every colour is an exact palette colour.
TEST(SegTruth, PngMappingEqualsSegLabelsExactly) {
  SmallPhantom& p = small_png();
  ColourMatcher matcher(read_palette(p.config.seg->palette), p.config.seg->tolerance);
  LabelStats stats;
  std::uint64_t wrong = 0;
  for (int k = 0; k < p.nz; ++k) {
    cv::Mat ids = map_colours(read_slice(p.seg_file(k)), matcher, true, p.seg_file(k), &stats);
    ASSERT_EQ(ids.size(), cv::Size(p.nx, p.ny));
    int w = cv::countNonZero(ids != p.slice16(p.seg_labels, k));
    EXPECT_EQ(w, 0) << "slice " << k;
    wrong += std::uint64_t(w);
  }
  std::printf("PNG seg mapping vs truth/seg_labels: %llu wrong of %llu\n",
              (unsigned long long)wrong, (unsigned long long)(std::uint64_t(p.nx) * p.ny * p.nz));
  EXPECT_EQ(stats.exact, std::uint64_t(p.nx) * p.ny * p.nz);
  EXPECT_EQ(stats.nearest, 0u);
  EXPECT_EQ(stats.unmatched, 0u);
}

// JPEG (quality 90, 4:2:0 chroma) blurs colours across boundaries. docs/GOALS.md §6's bar: >= 99.5
// % of the pixels inside the body (truth seg_labels > 0, i.e. the truth mask carried onto the
// drifted grid of each slice) get their true ID, over the whole 64-slice small phantom. Each slice
// must also reach 99 % (a bad slice cannot hide in the average; a body cross-section of ~20k pixels
// has ~2k boundary pixels, so 1 % is half of them). Outside the body (gel, background) only the
// body edge can be wrong: >= 99.5 % there too. Measured (seed 3): 99.67 % in the body, worst
// slice 99.43 %, 100 % outside (98.75 % in the body before unsure matches were decided by their
// neighbourhood, labels.cpp kConfidentDistance).
TEST(SegTruth, JpegMappingInsideBodyAtLeast995Percent) {
  SmallPhantom& p = small_jpeg();
  ColourMatcher matcher(read_palette(p.config.seg->palette), p.config.seg->tolerance);
  std::uint64_t body = 0, body_equal = 0, outside = 0, outside_equal = 0;
  double worst = 1.0;
  int worst_k = -1;
  for (int k = 0; k < p.nz; ++k) {
    cv::Mat ids = map_colours(read_slice(p.seg_file(k)), matcher, false, p.seg_file(k), nullptr);
    cv::Mat truth = p.slice16(p.seg_labels, k);
    cv::Mat in_body = truth > 0, equal = ids == truth;
    std::uint64_t b = std::uint64_t(cv::countNonZero(in_body));
    std::uint64_t be = std::uint64_t(cv::countNonZero(in_body & equal));
    body += b;
    body_equal += be;
    outside += truth.total() - b;
    outside_equal += std::uint64_t(cv::countNonZero(~in_body & equal));
    if (b > 0 && double(be) / b < worst) worst = double(be) / b, worst_k = k;
  }
  ASSERT_GT(body, 500000u);
  double in_body = double(body_equal) / body, out_body = double(outside_equal) / outside;
  std::printf(
      "JPEG seg mapping vs truth/seg_labels: %.4f %% in body (%llu px), %.4f %% outside, "
      "worst slice %d: %.4f %%\n",
      100 * in_body, (unsigned long long)body, 100 * out_body, worst_k, 100 * worst);
  EXPECT_GE(in_body, 0.995);
  EXPECT_GE(out_body, 0.995);
  EXPECT_GE(worst, 0.99) << "slice " << worst_k;
}

// Requirement 2 (resampled labels vs truth/labels.nrrd, TRUE transforms).
// 1. The stage adds nothing but the mapping and nearest-neighbour resampling: its output equals
//    resample_labels_nearest(truth/seg_labels) with the true transform, every pixel.
// 2. Why truth/labels.nrrd itself is not met everywhere: the phantom draws seg(p) = label(q(p))
//    at the observed pixel centres p; resampling back takes seg at round(p(q)), the label of a
//    model point up to sqrt(2)/2 = 0.71 px from q. So only pixels within 0.71 px of a boundary
//    can differ: asserted zero errors at pixels whose truth 3x3 neighbourhood is one label (a
//    boundary there is >= 1 px away). Overall: every boundary pixel is at risk, about half of
//    them flip (the boundary falls on either side of the half-way point with equal odds). On the
//    small phantom (seed 3; the black and the duplicated slice left out, compare_with_truth)
//    measured 98.98 % equal overall and 96.85 % in the body (truth mask, where the edges are):
//    asserted >= 98 % and >= 96 % (about one point of margin for the boundary share).
TEST(SegTruth, ResampledLabelsExactAwayFromEdges) {
  SmallPhantom& p = small_png();
  p.run_stage_with_true_transforms();
  std::vector<cv::Mat> out = read_label_slices(p.config, p.nz);
  // The expected labels, computed here from the ARCHITECTURE.md convention and not through the
  // library: output pixel q shows the seg pixel nearest to p = c + R(θ)(q - c) + d in the drawn
  // (drifted) slice, 0 outside it. Pixels whose p lies within 1e-6 px of a rounding boundary
  // (a tie between two source pixels) are left out.
  std::uint64_t wrong = 0, compared = 0, ties = 0;
  for (int k = 0; k < p.nz; ++k) {
    const cv::Mat seg = p.slice16(p.seg_labels, k);
    const auto& t = p.transforms.slices[std::size_t(k)];
    const double th = t.rigid.rotation_deg * M_PI / 180.0, cs = std::cos(th), sn = std::sin(th);
    const double cx = (p.nx - 1) / 2.0, cy = (p.ny - 1) / 2.0;
    for (int y = 0; y < p.ny; ++y)
      for (int x = 0; x < p.nx; ++x) {
        const double px = cx + cs * (x - cx) - sn * (y - cy) + t.rigid.dx_px;
        const double py = cy + sn * (x - cx) + cs * (y - cy) + t.rigid.dy_px;
        const double fx = px - std::floor(px), fy = py - std::floor(py);
        if (std::abs(fx - 0.5) < 1e-6 || std::abs(fy - 0.5) < 1e-6) {
          ++ties;
          continue;
        }
        const int ix = int(std::lround(px)), iy = int(std::lround(py));
        const std::uint16_t expected =
            ix >= 0 && iy >= 0 && ix < p.nx && iy < p.ny ? seg.at<std::uint16_t>(iy, ix) : 0;
        ++compared;
        if (out[std::size_t(k)].at<std::uint16_t>(y, x) != expected) ++wrong;
      }
  }
  std::printf("resampled labels: %llu of %llu differ from the nearest seg pixel (%llu ties)\n",
              (unsigned long long)wrong, (unsigned long long)compared, (unsigned long long)ties);
  EXPECT_EQ(wrong, 0u);
  EXPECT_LT(ties, compared / 1000);
  Agreement a = compare_with_truth(p.dir.path(), out);
  std::printf(
      "PNG seg, true transforms, small: %.4f %% equal, %.4f %% in body, %llu/%llu "
      "interior wrong\n",
      100 * a.fraction(), 100 * a.body_fraction(), (unsigned long long)a.interior_wrong,
      (unsigned long long)a.interior);
  EXPECT_EQ(a.interior_wrong, 0u);
  EXPECT_GT(a.interior, a.total * 8 / 10);
  EXPECT_GE(a.fraction(), 0.98);
  EXPECT_GE(a.body_fraction(), 0.96);
}

// The JPEG segmentation through the whole labels stage (true transforms): inside the body the
// labels equal the PNG result's on >= 99.5 % of the voxels (nearest-neighbour resampling only
// picks pixels of the mapped slice, so the mapping's 99.5 % carries over), and its agreement
// with truth/labels.nrrd in the body is within 0.5 point of the PNG result's.
TEST(SegTruth, JpegStageWithinTolerance) {
  SmallPhantom& png = small_png();
  SmallPhantom& jpeg = small_jpeg();
  png.run_stage_with_true_transforms();
  jpeg.run_stage_with_true_transforms();
  auto a = read_label_slices(png.config, png.nz), b = read_label_slices(jpeg.config, jpeg.nz);
  std::uint64_t body = 0, same = 0;
  for (int k = 0; k < png.nz; ++k) {
    cv::Mat m(png.ny, png.nx, CV_8UC1,
              png.mask.as<std::uint8_t>() + std::size_t(png.nx) * png.ny * k);
    body += std::uint64_t(cv::countNonZero(m));
    same += std::uint64_t(cv::countNonZero(m & (a[k] == b[k])));
  }
  ASSERT_GT(body, 500000u);
  Agreement ta = compare_with_truth(png.dir.path(), a), tb = compare_with_truth(jpeg.dir.path(), b);
  std::printf("JPEG vs PNG labels in body: %.4f %%; vs truth in body: PNG %.4f %%, JPEG %.4f %%\n",
              100.0 * same / body, 100 * ta.body_fraction(), 100 * tb.body_fraction());
  EXPECT_GE(double(same) / body, 0.995);
  EXPECT_GE(tb.body_fraction(), ta.body_fraction() - 0.005);
}

// End to end: the real register stage, then vispack-labels as an executable. Registration error
// moves a few more boundary pixels. Measured on tiny seed 3: 96.5 % equal overall, 87.7 % in the
// body (true transforms: 97.5 % / 91.1 %). Asserted >= 95 % overall and >= 85 % in the body,
// i.e. at most ~6 points below the true-transform case (the tiny body is mostly boundary).
TEST(LabelsStage, EndToEndThroughRegistration) {
  TempDir dir;
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 3;
  po.quiet = true;
  make_phantom(dir.path(), po);
  Config config = load_config(dir / "config.json");
  StageOptions options;
  options.quiet = true;
  run_register_stage(config, options);
  std::string out;
  int rc = test::run_command(
      test::bin("vispack-labels") + " --config " + dir / "config.json" + " --quiet", &out);
  ASSERT_EQ(rc, 0) << out;
  Agreement a = compare_with_truth(dir.path(), read_label_slices(config, 24));
  std::printf("PNG seg, registered: %.4f %% equal, %.4f %% in body\n", 100 * a.fraction(),
              100 * a.body_fraction());
  EXPECT_GE(a.fraction(), 0.95);
  EXPECT_GE(a.body_fraction(), 0.85);

  // Strict mode with a palette that lacks one colour: exit code 6 naming the file and pixel.
  auto palette = nlohmann::json::parse(read_file(dir / "palette.json"));
  palette["labels"].erase(0);  // drop "skin"
  write_file_atomic(dir / "palette.json", palette.dump());
  auto cfg = nlohmann::json::parse(read_file(dir / "config.json"));
  cfg["seg"]["strict"] = true;
  write_file_atomic(dir / "config.json", cfg.dump());
  rc = test::run_command(
      test::bin("vispack-labels") + " --config " + dir / "config.json" + " --quiet", &out);
  EXPECT_EQ(rc, 6) << out;
  EXPECT_NE(out.find("vispack-labels: error: "), std::string::npos) << out;
  EXPECT_NE(out.find("seg_"), std::string::npos) << out;
  EXPECT_NE(out.find("pixel ("), std::string::npos) << out;
}

// The CT anchor and the global solve on synthetic slices made here: an analytic body (skin/fat,
// muscle with texture, a bone ring, an air cavity the gel fills) rendered as CT (HU, 2× coarser,
// area-sampled) and as a colour slice in blue gel under a known rigid transform, with lighting
// and noise. Truth is the transform the colour slice was rendered with, in the CT-defined frame.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include <opencv2/imgproc.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/register.h"

namespace vp = vispack::pipeline;

namespace {

// The body of slice z in output-grid pixels: centre shifted by (shift_x, shift_y), size scaled.
struct Body {
  cv::Size size{256, 192};
  double shift_x = 0, shift_y = 0, scale = 1.0;
  double cavity_x = 0;  // the cavity's position moves with z in the anatomy test
  bool legs = false;    // two legs below the pelvis instead of one trunk (legs_tissue)
};

struct Tissue {
  float hu;
  cv::Vec3f rgb;
};

Tissue legs_tissue(const Body& b, double x, double y);

Tissue tissue(const Body& b, double x, double y) {
  if (b.legs) return legs_tissue(b, x, y);
  const double cx = (b.size.width - 1) * 0.5 + b.shift_x,
               cy = (b.size.height - 1) * 0.5 + b.shift_y;
  const double a = 0.36 * b.size.width * b.scale, bb = 0.34 * b.size.height * b.scale;
  const double u = (x - cx) / a, v = (y - cy) / bb;
  const double r = std::sqrt(u * u + v * v);
  const cv::Vec3f gel(40, 70, 160);
  if (r > 1.0) return {-1000.f, gel};
  const double tex =
      std::sin(0.31 * x + 0.7) * std::cos(0.23 * y - 0.4) + 0.5 * std::sin(0.11 * (x + y));
  if (r > 0.86) return {-100.f, cv::Vec3f(225, 205, 150)};            // fat under the skin
  if (r > 0.72 && r < 0.8) return {800.f, cv::Vec3f(235, 230, 215)};  // bone ring
  const double ux = (x - cx - (0.25 * a + b.cavity_x)) / (0.18 * a),
               vy = (y - cy + 0.2 * bb) / (0.14 * bb);
  if (ux * ux + vy * vy < 1.0) return {-900.f, cv::Vec3f(55, 85, 170)};  // air, gel-filled
  return {float(40 + 25 * tex), cv::Vec3f(float(150 + 30 * tex), float(60 + 10 * tex), 55)};
}

// Two legs of nearly the same size, 108 px apart (centre to centre), each skin, fat, muscle with
// texture and a bone (mirrored). The right leg is 1.5 px larger in the CT, but its outer 2.5 px
// are skin that looks nearly like the gel (colour distance 40: frost, or skin pressed against
// the gel), so in the colour slice it is the SMALLER leg: a largest-component reduction keeps
// the right leg of the CT and the left leg of the colour slice.
Tissue legs_tissue(const Body& b, double x, double y) {
  const cv::Vec3f gel(40, 70, 160);
  const double cx = (b.size.width - 1) * 0.5 + b.shift_x,
               cy = (b.size.height - 1) * 0.5 + b.shift_y;
  for (int side : {-1, 1}) {
    const double grow = side > 0 ? 1.5 : 0.0;  // the right leg is larger in the CT
    const double a = 40 + grow, bb = 46 + grow;
    const double lx = cx + side * 54, ly = cy + 4 * side;
    const double u = (x - lx) / a, v = (y - ly) / bb;
    const double r = std::sqrt(u * u + v * v);
    if (r > 1.0) continue;
    // Depth below the skin, pixels (first order).
    const double depth = (1.0 - r) * std::min(a, bb);
    if (side > 0 && depth < 2.5) return {30.f, cv::Vec3f(70, 95, 150)};  // gel-like skin
    if (depth < 6) return {-100.f, cv::Vec3f(225, 205, 150)};            // fat
    const double bx = (x - (lx - side * 8)) / 11, by = (y - (ly - 6)) / 12;
    if (bx * bx + by * by < 1.0) return {900.f, cv::Vec3f(235, 230, 215)};  // femur
    const double tex =
        std::sin(0.31 * x + 0.7) * std::cos(0.23 * y - 0.4) + 0.5 * std::sin(0.11 * (x + y));
    return {float(45 + 25 * tex), cv::Vec3f(float(150 + 30 * tex), float(60 + 10 * tex), 55)};
  }
  return {-1000.f, gel};
}

// CT slice (Wct × Hct, HU) for the output frame `f` (CT pixel u → output q), 3×3 supersampled.
cv::Mat render_ct(const Body& b, cv::Size ct_size, const vp::Similarity& f) {
  const cv::Matx23d m =
      vp::similarity_matrix(f, vp::image_centre(ct_size), vp::image_centre(b.size));
  cv::Mat ct(ct_size, CV_32F);
  for (int y = 0; y < ct_size.height; ++y)
    for (int x = 0; x < ct_size.width; ++x) {
      double sum = 0;
      for (int j = 0; j < 3; ++j)
        for (int i = 0; i < 3; ++i) {
          const double ux = x + (i - 1) / 3.0, uy = y + (j - 1) / 3.0;
          sum += tissue(b, m(0, 0) * ux + m(0, 1) * uy + m(0, 2),
                        m(1, 0) * ux + m(1, 1) * uy + m(1, 2))
                     .hu;
        }
      ct.at<float>(y, x) = float(sum / 9.0);
    }
  return ct;
}

// Observed colour slice: observed(p) = body(T⁻¹(p)), 2×2 supersampled, gain, noise σ 3.
cv::Mat render_colour(const Body& b, const vp::Rigid& t, unsigned seed, double gain = 1.0) {
  const cv::Matx23d inv = vp::invert_affine(vp::rigid_matrix(t, vp::image_centre(b.size)));
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.f, 3.f);
  cv::Mat out(b.size, CV_8UC3);
  for (int y = 0; y < b.size.height; ++y)
    for (int x = 0; x < b.size.width; ++x) {
      cv::Vec3f sum(0, 0, 0);
      for (int j = 0; j < 2; ++j)
        for (int i = 0; i < 2; ++i) {
          const double px = x + (i - 0.5) / 2.0, py = y + (j - 0.5) / 2.0;
          sum += tissue(b, inv(0, 0) * px + inv(0, 1) * py + inv(0, 2),
                        inv(1, 0) * px + inv(1, 1) * py + inv(1, 2))
                     .rgb;
        }
      for (int c = 0; c < 3; ++c)
        out.at<cv::Vec3b>(y, x)[c] =
            cv::saturate_cast<std::uint8_t>(sum[c] / 4.0 * gain + noise(rng));
    }
  return out;
}

// Largest displacement (corners and centre) between two transforms of a slice of `size`.
double error_px(const vp::Rigid& a, const vp::Rigid& b, cv::Size size) {
  const cv::Point2d c = vp::image_centre(size);
  return vp::rigid_motion_px(
      vp::rigid_from_matrix(
          vp::compose_affine(vp::rigid_matrix(a, c), vp::invert_affine(vp::rigid_matrix(b, c))), c),
      size);
}

const vp::Similarity kFrame{2.0, 0.0, 0.0, 0.0};  // CT pixels twice the colour pixels
const cv::Size kCtSize{150, 120};                 // larger field of view than the colour slice

vp::AnchorEstimate anchor_of(const Body& body, const vp::Rigid& t,
                             const vp::Similarity& frame = kFrame, unsigned seed = 1) {
  vp::RegisterOptions options;
  const cv::Mat colour = render_colour(body, t, seed, 0.93);
  const vp::RegisterFrame f = vp::prepare_frame(colour, options, 1.0 / frame.scale);
  return vp::estimate_ct_anchor(f, render_ct(body, kCtSize, frame), frame, {});
}

}  // namespace

// Accuracy and capture range. Tolerance: 0.4 px at the corners of the 256×192 slice (0.2 CT
// px; at the body's edge about half that): what one slice's anchor gives here (worst of the five
// cases 0.36 px; 0.35 was the bound before the outline step, which trades a little on this
// body, whose colour → HU relation the polynomial fits almost exactly, for the rotation of small
// bodies on the realistic cases, docs/BENCHMARKS.md). The largest case (18 px, 6°)
// must be captured and refined to the same accuracy.
struct AnchorCase {
  vp::Rigid t;
};
class AnchorTest : public ::testing::TestWithParam<AnchorCase> {};

TEST_P(AnchorTest, RecoversTheTransformAgainstCt) {
  const Body body;
  const vp::Rigid t = GetParam().t;
  const vp::AnchorEstimate a = anchor_of(body, t);
  ASSERT_TRUE(a.ok);
  EXPECT_GT(a.confidence, 0.8);
  EXPECT_GT(a.correlation, 0.8);
  const double e = error_px(a.transform, t, body.size);
  RecordProperty("error_px", std::to_string(e));
  EXPECT_LT(e, 0.4) << a.transform.rotation_deg << " " << a.transform.dx_px << " "
                    << a.transform.dy_px;
  EXPECT_NEAR(a.radius_px, 0.36 * 256 * 0.6, 20.0);  // radius of gyration of the ellipse body
}

INSTANTIATE_TEST_SUITE_P(Synthetic, AnchorTest,
                         ::testing::Values(AnchorCase{{0.0, 0.0, 0.0}},
                                           AnchorCase{{0.0, 0.4, -0.7}},
                                           AnchorCase{{1.2, -2.3, 1.6}},
                                           AnchorCase{{-2.5, 6.0, -4.0}},
                                           AnchorCase{{6.0, 18.0, -9.0}}));

// Two legs of nearly the same size (docs/ARCHITECTURE.md, 'The body mask: every part is body'): the
// anchor matches all parts at once, so the alignment that overlaps both legs wins over one that
// lays one leg on the other, up to the male's block jumps (29 px, 7°). With each side reduced to
// its largest part (legs_tissue: the right leg in the CT, the left one in the colour slice) the
// anchor locked the legs onto each other (tried: all five cases fail, 116-121 px off, correlation
// 0.47-0.76); with all parts but the capture's phase correlation alone (no overlap candidate),
// (−7°, −29, 10) was not captured.
class TwoLegsAnchor : public ::testing::TestWithParam<AnchorCase> {};

TEST_P(TwoLegsAnchor, RecoversTheTransformNotTheOtherLeg) {
  Body legs;
  legs.size = cv::Size(320, 192);
  legs.legs = true;
  const vp::Rigid t = GetParam().t;
  vp::RegisterOptions options;
  const cv::Mat colour = render_colour(legs, t, 3, 0.95);
  const vp::RegisterFrame f = vp::prepare_frame(colour, options, 1.0 / kFrame.scale);
  const vp::AnchorEstimate a =
      vp::estimate_ct_anchor(f, render_ct(legs, cv::Size(180, 120), kFrame), kFrame, {});
  ASSERT_TRUE(a.ok);
  const double e = error_px(a.transform, t, legs.size);
  RecordProperty("error_px", std::to_string(e));
  EXPECT_LT(e, 0.5) << a.transform.rotation_deg << " " << a.transform.dx_px << " "
                    << a.transform.dy_px;
  EXPECT_GT(a.correlation, 0.8);
}

INSTANTIATE_TEST_SUITE_P(Synthetic, TwoLegsAnchor,
                         ::testing::Values(AnchorCase{{0.0, 0.0, 0.0}},
                                           AnchorCase{{7.0, 29.0, -12.0}},
                                           AnchorCase{{-7.0, -29.0, 10.0}},
                                           AnchorCase{{-3.0, 29.0, 20.0}},
                                           AnchorCase{{5.0, -15.0, -25.0}}));

TEST(CtAnchor, FollowsTheDefinedOutputFrame) {
  // An output frame turned by 3° and shifted: the same observed slice maps differently.
  const Body body;
  const vp::Similarity frame{2.0, 3.0, 4.0, -2.0};
  const vp::Rigid t{1.0, 2.0, 1.0};
  const vp::AnchorEstimate a = anchor_of(body, t, frame);
  ASSERT_TRUE(a.ok);
  EXPECT_LT(error_px(a.transform, t, body.size), 0.35);
}

TEST(CtAnchor, ConfidenceFallsOnTinyAndEmptySlices) {
  Body tiny;
  tiny.scale = 0.12;  // the end of the stack: a small patch of body
  const vp::AnchorEstimate a = anchor_of(tiny, {0.5, 1.0, -1.0});
  EXPECT_LT(a.confidence, 0.5);
  EXPECT_LT(a.radius_px, 12.0);
  Body none;
  none.scale = 0.0;
  const vp::AnchorEstimate b = anchor_of(none, {0, 0, 0});
  EXPECT_FALSE(b.ok);
  EXPECT_EQ(b.confidence, 0.0);
  // JSON round trip.
  const vp::AnchorEstimate c = vp::anchor_from_json(vp::to_json(a), "test");
  EXPECT_DOUBLE_EQ(c.transform.dx_px, a.transform.dx_px);
  EXPECT_DOUBLE_EQ(c.confidence, a.confidence);
  EXPECT_THROW(vp::anchor_from_json(nlohmann::json{{"ok", true}}, "x"), vispack::FormatError);
}

namespace {

// A stack whose anatomy moves steadily along z (the body drifts 0.4 px per slice in y and its
// cavity 0.3 px per slice in x, the body shrinks towards the ends) while the TRUE drift is only
// the colour camera's constant offset against the CT plus a small random walk (σ 0.05 px).
struct Stack {
  std::vector<cv::Mat> colour, ct;
  std::vector<vp::Rigid> truth;
};
Stack anatomy_stack(int n, unsigned seed) {
  Stack s;
  std::mt19937 rng(seed);
  std::normal_distribution<double> step(0.0, 0.05);
  vp::Rigid t{0.8, 3.0, -2.0};  // camera offset against the CT frame
  for (int k = 0; k < n; ++k) {
    Body b;
    b.shift_y = 0.4 * k - 0.2 * n;  // the outline rises 0.4 px per slice
    b.cavity_x = 0.3 * k - 0.15 * n;
    const double z = (k + 0.5) / n;
    b.scale = std::min(1.0, 0.25 + 3.0 * std::min(z, 1.0 - z));  // tapers at both ends
    t.dx_px += step(rng), t.dy_px += step(rng), t.rotation_deg += 0.1 * step(rng);
    s.truth.push_back(t);
    s.colour.push_back(render_colour(b, t, seed * 1000 + unsigned(k), 1.0 + 0.04 * std::sin(k)));
    s.ct.push_back(render_ct(b, kCtSize, kFrame));
  }
  return s;
}

struct StackErrors {
  double rms = 0, max = 0;
};
StackErrors errors(const std::vector<vp::SliceTransform>& got, const std::vector<vp::Rigid>& truth,
                   cv::Size size) {
  StackErrors e;
  for (std::size_t k = 0; k < truth.size(); ++k) {
    const double d = error_px(got[k].rigid, truth[k], size);
    e.rms += d * d, e.max = std::max(e.max, d);
  }
  e.rms = std::sqrt(e.rms / double(truth.size()));
  return e;
}

std::vector<vp::SlicePairs> records(const Stack& s) {
  vp::RegisterOptions options;
  return vp::compute_pairs(
      0, int(s.colour.size()),
      [&](int k) { return vp::prepare_frame(s.colour[std::size_t(k)], options, 0.5); }, options, 2,
      [&](int k, const vp::RegisterFrame& f) -> std::optional<vp::AnchorEstimate> {
        return vp::estimate_ct_anchor(f, s.ct[std::size_t(k)], kFrame, {});
      });
}

}  // namespace

// The issue's case: slice-to-slice registration follows the anatomy and integrates it as drift
// (here ~0.4 px per slice), the CT-anchored solve does not: its error stays below one bound
// (0.3 px RMS, well inside the 0.5 px goal) at 20 and at 40 slices.
TEST(RegisterSolve, AnatomyMotionDoesNotAccumulate) {
  StackErrors anchored[2], chained[2];
  const int lengths[2] = {20, 40};
  for (int i = 0; i < 2; ++i) {
    const Stack s = anatomy_stack(lengths[i], 5);
    const auto recs = records(s);
    vp::StackSolveOptions so;
    so.anchor = "ct";
    const vp::StackSolve solved = vp::solve_stack(recs, s.colour[0].size(), so);
    EXPECT_EQ(solved.frame, "ct");
    anchored[i] = errors(solved.slices, s.truth, s.colour[0].size());
    // Pairs alone, referenced to slice 0's true transform (their best case).
    auto chain = vp::chain_transforms(recs, s.colour[0].size(), 6.0);
    const cv::Point2d c = vp::image_centre(s.colour[0].size());
    for (auto& t : chain) {
      const vp::Rigid r = vp::rigid_from_matrix(
          vp::compose_affine(vp::rigid_matrix(t.rigid, c), vp::rigid_matrix(s.truth[0], c)), c);
      t.rigid = r;
    }
    chained[i] = errors(chain, s.truth, s.colour[0].size());
    for (const auto& t : solved.slices)
      EXPECT_FALSE(t.jump) << t.index;
    RecordProperty(vispack::cat("anchored_rms_", lengths[i]), std::to_string(anchored[i].rms));
    std::printf("n %d: anchored rms %.3f max %.3f; chained rms %.3f max %.3f\n", lengths[i],
                anchored[i].rms, anchored[i].max, chained[i].rms, chained[i].max);
  }
  // One bound for both lengths (no growth), well inside the 0.5 px goal.
  EXPECT_LE(anchored[0].rms, 0.3);
  EXPECT_LE(anchored[1].rms, 0.3);
  EXPECT_LE(anchored[1].max, 1.0);
  // The pair chain does integrate the anatomy (and loses track where the body is small).
  EXPECT_GT(chained[0].max, 5.0);
  EXPECT_GT(chained[1].max, 5.0);
}

// A person's corrections win: a fixed transform is kept exactly, a marked jump is flagged and
// cuts the pair terms, an excluded anchor takes no part (its slice still gets a transform from
// its neighbours, close to the truth), and the override file is checked key by key.
TEST(RegisterSolve, OverridesWin) {
  const Stack s = anatomy_stack(12, 9);
  const auto recs = records(s);
  const cv::Size size = s.colour[0].size();
  vp::StackSolveOptions so;
  so.anchor = "ct";
  vp::SliceOverride fix;
  fix.index = 3;
  fix.transform = vp::Rigid{1.5, 10.0, -4.0};
  vp::SliceOverride jump;
  jump.index = 7;
  jump.jump = true;
  vp::SliceOverride excl;
  excl.index = 5;
  excl.exclude_anchor = true;
  so.overrides = {fix, jump, excl};
  const vp::StackSolve solved = vp::solve_stack(recs, size, so);
  EXPECT_NEAR(solved.slices[3].rigid.dx_px, 10.0, 1e-6);
  EXPECT_NEAR(solved.slices[3].rigid.rotation_deg, 1.5, 1e-6);
  EXPECT_TRUE(solved.slices[7].jump);
  // (3 and 4 may differ by the fixed transform's arbitrary 10 px: a jump there is the truth
  // of the corrected stack.)
  for (int k : {1, 2, 5, 6, 8, 9, 10})
    EXPECT_FALSE(solved.slices[std::size_t(k)].jump) << k;
  EXPECT_LT(error_px(solved.slices[5].rigid, s.truth[5], size), 0.6);
  EXPECT_EQ(solved.anchors_used, 10);  // 12 slices, one fixed, one excluded
  // The file form.
  vispack::test::TempDir dir("vispack-overrides");
  const std::string path = dir / "o.json";
  vispack::write_file_atomic(path, R"({"_c": 1, "slices": [{"index": 3, "transform":
      {"rotation_deg": 1.5, "dx_px": 10, "dy_px": -4}}, {"index": 7, "jump": true},
      {"index": 5, "anchor": false, "note": "knife mark"}]})");
  const auto read = vp::read_overrides(path, 12);
  ASSERT_EQ(read.size(), 3u);
  EXPECT_TRUE(read[0].transform.has_value());
  EXPECT_TRUE(read[1].jump);
  EXPECT_TRUE(read[2].exclude_anchor);
  EXPECT_EQ(read[2].note, "knife mark");
  vispack::write_file_atomic(path, R"({"slices": [{"index": 12}]})");
  EXPECT_THROW(vp::read_overrides(path, 12), vispack::ConfigError);
  vispack::write_file_atomic(path, R"({"slices": [{"index": 1, "jmup": true}]})");
  EXPECT_THROW(vp::read_overrides(path, 12), vispack::ConfigError);
}

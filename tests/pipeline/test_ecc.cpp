// The fused Euclidean ECC (register/ecc.h) against OpenCV's cv::findTransformECC on the same
// images and start (the reference it reimplements), and against the true motion of synthetic
// images warped by a known rotation + translation with exact (double) resampling.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/pipeline/register/ecc.h"

namespace vp = vispack::pipeline;

namespace {

// Smooth random texture (σ = `sigma` px) with a bright disc and a dark bar: structure at several
// scales, values 0..1, CV_32F.
cv::Mat texture(cv::Size size, unsigned seed, double sigma) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.f, 1.f);
  cv::Mat tex(size, CV_32F);
  for (int y = 0; y < size.height; ++y)
    for (int x = 0; x < size.width; ++x)
      tex.at<float>(y, x) = noise(rng);
  cv::GaussianBlur(tex, tex, cv::Size(0, 0), sigma);
  cv::normalize(tex, tex, 0, 1, cv::NORM_MINMAX);
  cv::circle(tex, cv::Point(size.width / 3, size.height / 2), size.height / 5, cv::Scalar(1.2), -1);
  cv::rectangle(tex, cv::Rect(size.width / 2, size.height / 4, size.width / 4, size.height / 10),
                cv::Scalar(-0.3), -1);
  cv::GaussianBlur(tex, tex, cv::Size(0, 0), 1.5);
  return tex;
}

// Template → input matrix of a rotation by θ about `c` followed by a shift d:
// q = c + R(θ)(p − c) + d.
cv::Matx23d rigid(double theta_deg, cv::Point2d d, cv::Point2d c) {
  const double a = theta_deg * vispack::kPi / 180.0, ca = std::cos(a), sa = std::sin(a);
  return {ca, -sa, c.x - ca * c.x + sa * c.y + d.x, sa, ca, c.y - sa * c.x - ca * c.y + d.y};
}

// input(q) sampled at template pixel p: input(m · p), bicubic, so the template is the input
// seen through m (the pixels whose source leaves the input are 0: ECC's mask ignores them).
cv::Mat warp_to_template(const cv::Mat& input, const cv::Matx23d& m, cv::Size size) {
  cv::Mat out;
  cv::warpAffine(input, out, cv::Mat(m), size, cv::INTER_CUBIC | cv::WARP_INVERSE_MAP,
                 cv::BORDER_REFLECT);
  return out;
}

// Largest displacement between two template → input matrices over the template's corners.
double max_corner_px(const cv::Matx23d& a, const cv::Matx23d& b, cv::Size size) {
  double worst = 0;
  for (double x : {0.0, double(size.width - 1)})
    for (double y : {0.0, double(size.height - 1)}) {
      const cv::Vec3d p(x, y, 1.0);
      const cv::Vec2d d = a * p - b * p;
      worst = std::max(worst, std::hypot(d[0], d[1]));
    }
  return worst;
}

struct OpenCvResult {
  bool ok = false;
  double rho = 0;
  cv::Matx23d warp;
};

OpenCvResult opencv_ecc(const cv::Mat& tmpl, const cv::Mat& input, const cv::Matx23d& start,
                        const vp::EccOptions& o) {
  cv::Mat w(2, 3, CV_32F);
  for (int i = 0; i < 6; ++i)
    w.at<float>(i / 3, i % 3) = float(start.val[i]);
  OpenCvResult r;
  try {
    r.rho = cv::findTransformECC(
        tmpl, input, w, cv::MOTION_EUCLIDEAN,
        cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, o.iterations, o.eps),
        cv::noArray(), o.blur_size);
    r.ok = true;
  } catch (const cv::Exception&) {
    r.ok = false;
  }
  for (int i = 0; i < 6; ++i)
    r.warp.val[i] = w.at<float>(i / 3, i % 3);
  return r;
}

// Runs OpenCV's ECC and the fused one from `start` and checks they end at the same place with
// the same correlation; returns the fused result.
cv::Matx23d expect_same_as_opencv(const cv::Mat& tmpl, const cv::Mat& input,
                                  const cv::Matx23d& start, const vp::EccOptions& o) {
  const OpenCvResult ref = opencv_ecc(tmpl, input, start, o);
  EXPECT_TRUE(ref.ok);
  cv::Matx23d ours = start;
  const std::optional<double> rho = vp::ecc_euclidean(tmpl, input, ours, o);
  EXPECT_TRUE(rho.has_value());
  if (!ref.ok || !rho) return ours;
  EXPECT_NEAR(*rho, ref.rho, 2e-5);
  EXPECT_LT(max_corner_px(ours, ref.warp, tmpl.size()), 0.01);
  return ours;
}

struct Case {
  double theta_deg;
  cv::Point2d shift;
  int blur;
};

}  // namespace

// Same images, same start: the fused iteration ends where OpenCV's does (within OpenCV's 1/32 px
// interpolation rounding), with the same correlation; and both end at the true motion.
TEST(Ecc, AgreesWithOpenCvAndFindsTheTrueMotion) {
  const cv::Size in_size(420, 300), t_size(400, 280);
  const cv::Mat input = texture(in_size, 7, 4.0);
  const cv::Point2d c(0.5 * (t_size.width - 1), 0.5 * (t_size.height - 1));
  for (const Case& k : {Case{1.7, {3.3, -2.6}, 1}, Case{-4.0, {-6.2, 5.4}, 3},
                        Case{0.35, {0.41, 0.77}, 5}, Case{8.0, {12.0, -9.5}, 5}}) {
    SCOPED_TRACE(testing::Message() << "theta " << k.theta_deg << " shift " << k.shift.x << ","
                                    << k.shift.y << " blur " << k.blur);
    const cv::Matx23d truth = rigid(k.theta_deg, k.shift + cv::Point2d(10, 10), c);
    const cv::Mat tmpl = warp_to_template(input, truth, t_size);
    // Start off by ~2 px and a fraction of the rotation, as the callers' coarse steps leave it.
    const cv::Matx23d start = rigid(0.8 * k.theta_deg, k.shift + cv::Point2d(11.6, 8.7), c);
    vp::EccOptions o;
    o.iterations = 100;
    o.eps = 1e-7;
    o.blur_size = k.blur;
    const cv::Matx23d ours = expect_same_as_opencv(tmpl, input, start, o);
    EXPECT_LT(max_corner_px(ours, truth, t_size), 0.03);
    EXPECT_LT(max_corner_px(opencv_ecc(tmpl, input, start, o).warp, truth, t_size), 0.03);
    // The result is a rotation.
    EXPECT_NEAR(ours(0, 0), ours(1, 1), 1e-12);
    EXPECT_NEAR(ours(0, 1), -ours(1, 0), 1e-12);
  }
}

// A different modality: the template is a non-monotonic intensity map of the input plus noise
// (the CT-anchor case), the iteration capped at a few updates: after the same number of updates
// both stand at the same place.
TEST(Ecc, SameStepsAsOpenCvOnAMultimodalPair) {
  const cv::Size size(360, 260);
  const cv::Mat input = texture(size, 11, 3.0);
  const cv::Point2d c(0.5 * (size.width - 1), 0.5 * (size.height - 1));
  const cv::Matx23d truth = rigid(-2.5, {4.2, 3.1}, c);
  cv::Mat tmpl = warp_to_template(input, truth, size);
  cv::Mat mapped(size, CV_32F);
  std::mt19937 rng(3);
  std::normal_distribution<float> noise(0.f, 0.02f);
  for (int y = 0; y < size.height; ++y)
    for (int x = 0; x < size.width; ++x) {
      const float v = tmpl.at<float>(y, x);
      mapped.at<float>(y, x) = 0.2f + 1.5f * v - 0.9f * v * v + noise(rng);
    }
  for (int iterations : {1, 3, 60}) {
    SCOPED_TRACE(testing::Message() << iterations << " iterations");
    vp::EccOptions o;
    o.iterations = iterations;
    o.eps = 1e-9;
    o.blur_size = 3;
    const cv::Matx23d start = rigid(-1.5, {2.5, 4.5}, c);
    expect_same_as_opencv(mapped, input, start, o);
  }
}

// 8-bit input is converted as OpenCV converts it; a template that maps outside the input, and
// images with nothing to correlate, are failures, not results.
TEST(Ecc, FailuresAreReported) {
  const cv::Size size(200, 150);
  const cv::Mat input = texture(size, 5, 3.0);
  cv::Mat input8;
  input.convertTo(input8, CV_8U, 200.0);
  const cv::Point2d c(0.5 * (size.width - 1), 0.5 * (size.height - 1));
  const cv::Matx23d truth = rigid(1.0, {2.0, -1.0}, c);
  cv::Mat tmpl8;
  warp_to_template(input8, truth, size).convertTo(tmpl8, CV_8U);
  cv::Matx23d w = rigid(0.0, {0, 0}, c);
  const std::optional<double> rho = vp::ecc_euclidean(tmpl8, input8, w, {});
  ASSERT_TRUE(rho.has_value());
  EXPECT_GT(*rho, 0.95);
  EXPECT_LT(max_corner_px(w, truth, size), 0.1);

  cv::Matx23d away = rigid(0.0, {5000, 0}, c);  // every template pixel maps outside
  EXPECT_FALSE(vp::ecc_euclidean(tmpl8, input8, away, {}).has_value());
  const cv::Mat flat(size, CV_32F, cv::Scalar(0.5));  // no variance: no correlation
  cv::Matx23d w2 = rigid(0.0, {0, 0}, c);
  EXPECT_FALSE(vp::ecc_euclidean(flat, input, w2, {}).has_value());
  EXPECT_THROW(vp::ecc_euclidean(cv::Mat(2, 2, CV_32F, cv::Scalar(0)), input, w2, {}),
               vispack::Error);
  vp::EccOptions even;
  even.blur_size = 4;
  EXPECT_THROW(vp::ecc_euclidean(tmpl8, input8, w2, even), vispack::Error);
}

// A 300×220 textured input, the template it shows through a rotation by θ about the centre and
// a shift d, and the identity start: the case of the tests of the options below.
struct MovedCase {
  cv::Size size{300, 220};
  cv::Point2d c{0.5 * (300 - 1), 0.5 * (220 - 1)};
  cv::Mat input, tmpl;
  cv::Matx23d truth, start;
  MovedCase(unsigned seed, double theta_deg, cv::Point2d d)
      : input(texture(size, seed, 3.0)),
        truth(rigid(theta_deg, d, c)),
        start(rigid(0.0, {0.0, 0.0}, c)) {
    tmpl = warp_to_template(input, truth, size);
  }
};

// The caller's divergence test (EccOptions::diverged): asked after every update with that
// update's warp; the first true ends the refinement as a failure with `warp` at that update; a
// test that never fires leaves every step, and so the result, as without one.
TEST(Ecc, DivergenceTestEndsTheIterationAtTheFirstIterateBeyondTheReach) {
  const MovedCase mc(9, 1.2, {3.0, -2.0});
  const cv::Size size = mc.size;
  const cv::Mat &input = mc.input, &tmpl = mc.tmpl;
  const cv::Matx23d truth = mc.truth, start = mc.start;
  vp::EccOptions plain;
  plain.iterations = 40;
  plain.eps = 1e-9;
  cv::Matx23d free_warp = start;
  const std::optional<double> free_rho = vp::ecc_euclidean(tmpl, input, free_warp, plain);
  ASSERT_TRUE(free_rho.has_value());
  EXPECT_LT(max_corner_px(free_warp, truth, size), 0.05);

  // A reach that the path never leaves: the same result, bit for bit.
  vp::EccOptions wide = plain;
  int asked = 0;
  wide.diverged = [&](const cv::Matx23d&) { return ++asked < 0; };
  cv::Matx23d wide_warp = start;
  const std::optional<double> wide_rho = vp::ecc_euclidean(tmpl, input, wide_warp, wide);
  ASSERT_TRUE(wide_rho.has_value());
  EXPECT_EQ(*wide_rho, *free_rho);
  EXPECT_EQ(cv::norm(cv::Mat(wide_warp), cv::Mat(free_warp), cv::NORM_INF), 0.0);
  EXPECT_GT(asked, 1);

  // A reach of 1 px in translation from the start: the path (which travels ~3.6 px) stops at its
  // first iterate beyond it, reported as a failure, the warp at that iterate.
  vp::EccOptions near = plain;
  std::vector<cv::Matx23d> iterates;
  near.diverged = [&](const cv::Matx23d& w) {
    iterates.push_back(w);
    return std::hypot(w(0, 2) - start(0, 2), w(1, 2) - start(1, 2)) > 1.0;
  };
  cv::Matx23d near_warp = start;
  EXPECT_FALSE(vp::ecc_euclidean(tmpl, input, near_warp, near).has_value());
  ASSERT_FALSE(iterates.empty());
  EXPECT_LT(int(iterates.size()), asked);
  for (std::size_t i = 0; i + 1 < iterates.size(); ++i)
    EXPECT_LE(std::hypot(iterates[i](0, 2) - start(0, 2), iterates[i](1, 2) - start(1, 2)), 1.0);
  EXPECT_EQ(cv::norm(cv::Mat(near_warp), cv::Mat(iterates.back()), cv::NORM_INF), 0.0);
}

// The step stop (EccOptions::min_step_px): the path is the same as without it up to the first
// update whose bound |Δt| + |Δθ| · diagonal falls under min_step_px, and ends there, as a
// success, within that step's reach of the full path's end; 0 leaves every step as before.
TEST(Ecc, StepStopEndsAtTheFirstUpdateSmallerThanTheMinimumStep) {
  const MovedCase mc(11, 1.5, {4.0, -3.0});
  const cv::Size size = mc.size;
  const cv::Mat &input = mc.input, &tmpl = mc.tmpl;
  const cv::Matx23d truth = mc.truth, start = mc.start;
  const double diagonal = std::hypot(size.width - 1, size.height - 1);
  // The full path (eps too small to stop it before the cap), every iterate recorded.
  auto run = [&](double min_step, std::vector<cv::Matx23d>& iterates, cv::Matx23d& warp) {
    vp::EccOptions o;
    o.iterations = 30;
    o.eps = 1e-12;
    o.min_step_px = min_step;
    o.diverged = [&](const cv::Matx23d& w) {
      iterates.push_back(w);
      return false;
    };
    warp = start;
    return vp::ecc_euclidean(tmpl, input, warp, o);
  };
  std::vector<cv::Matx23d> full_path;
  cv::Matx23d full_warp;
  ASSERT_TRUE(run(0.0, full_path, full_warp).has_value());
  EXPECT_LT(max_corner_px(full_warp, truth, size), 0.05);
  auto bound = [&](const cv::Matx23d& a, const cv::Matx23d& b) {
    return std::hypot(b(0, 2) - a(0, 2), b(1, 2) - a(1, 2)) +
           std::abs(std::asin(b(1, 0)) - std::asin(a(1, 0))) * diagonal;
  };
  // The first update under 0.02 px, away from the threshold (no rounding decides it).
  const double min_step = 0.02;
  std::size_t first_small = 0;
  for (cv::Matx23d prev = start; first_small < full_path.size(); prev = full_path[first_small++])
    if (bound(prev, full_path[first_small]) < min_step) break;
  ASSERT_LT(first_small + 2, full_path.size()) << "the full path must run on past that update";
  ASSERT_GT(first_small, 0u);
  const double at_stop = bound(full_path[first_small - 1], full_path[first_small]);
  ASSERT_LT(at_stop, 0.9 * min_step);
  ASSERT_GT(
      bound(first_small >= 2 ? full_path[first_small - 2] : start, full_path[first_small - 1]),
      1.1 * min_step);

  std::vector<cv::Matx23d> path;
  cv::Matx23d warp;
  const std::optional<double> rho = run(min_step, path, warp);
  ASSERT_TRUE(rho.has_value());
  ASSERT_EQ(path.size(), first_small + 1);  // stopped right after that update
  for (std::size_t i = 0; i < path.size(); ++i)
    EXPECT_EQ(cv::norm(cv::Mat(path[i]), cv::Mat(full_path[i]), cv::NORM_INF), 0.0) << i;
  EXPECT_EQ(cv::norm(cv::Mat(warp), cv::Mat(path.back()), cv::NORM_INF), 0.0);
  EXPECT_LT(max_corner_px(warp, full_warp, size), min_step);
  EXPECT_LT(max_corner_px(warp, truth, size), 0.05);

  // min_step_px 0: every step as without the option; a negative one is refused.
  std::vector<cv::Matx23d> again;
  cv::Matx23d again_warp;
  ASSERT_TRUE(run(0.0, again, again_warp).has_value());
  EXPECT_EQ(again.size(), full_path.size());
  EXPECT_EQ(cv::norm(cv::Mat(again_warp), cv::Mat(full_warp), cv::NORM_INF), 0.0);
  vp::EccOptions bad;
  bad.min_step_px = -1.0;
  cv::Matx23d w = start;
  EXPECT_THROW(vp::ecc_euclidean(tmpl, input, w, bad), vispack::Error);
}

// The give-up test (EccOptions::give_up): asked after every update with the correlation measured
// before it (the value a stop there returns) and the update's number; one that never fires leaves
// every step as without it; the first true ends the refinement as a failure, `warp` at that
// update.
TEST(Ecc, GiveUpSeesEveryUpdatesCorrelationAndEndsAsAFailure) {
  const MovedCase mc(13, 1.0, {3.0, 2.0});
  const cv::Mat &input = mc.input, &tmpl = mc.tmpl;
  vp::EccOptions o;
  o.iterations = 12;
  o.eps = 1e-12;
  std::vector<cv::Matx23d> path;
  o.diverged = [&](const cv::Matx23d& w) {
    path.push_back(w);
    return false;
  };
  cv::Matx23d free_warp = mc.start;
  const std::optional<double> free_rho = vp::ecc_euclidean(tmpl, input, free_warp, o);
  ASSERT_TRUE(free_rho.has_value());
  ASSERT_GE(path.size(), 4u);

  // Never fires: the same result, bit for bit; updates numbered 1, 2, ...; the last correlation
  // seen is the one returned.
  std::vector<double> seen;
  vp::EccOptions watch = o;
  watch.diverged = {};
  watch.give_up = [&](double rho, int update) {
    EXPECT_EQ(update, int(seen.size()) + 1);
    seen.push_back(rho);
    return false;
  };
  cv::Matx23d watched = mc.start;
  const std::optional<double> watched_rho = vp::ecc_euclidean(tmpl, input, watched, watch);
  ASSERT_TRUE(watched_rho.has_value());
  EXPECT_EQ(*watched_rho, *free_rho);
  EXPECT_EQ(cv::norm(cv::Mat(watched), cv::Mat(free_warp), cv::NORM_INF), 0.0);
  ASSERT_EQ(seen.size(), path.size());
  EXPECT_EQ(seen.back(), *free_rho);

  // Giving up at the third update: a failure, the warp at that update.
  vp::EccOptions quit = o;
  quit.diverged = {};
  quit.give_up = [&](double rho, int update) {
    EXPECT_EQ(rho, seen[std::size_t(update - 1)]);
    return update >= 3;
  };
  cv::Matx23d quit_warp = mc.start;
  EXPECT_FALSE(vp::ecc_euclidean(tmpl, input, quit_warp, quit).has_value());
  EXPECT_EQ(cv::norm(cv::Mat(quit_warp), cv::Mat(path[2]), cv::NORM_INF), 0.0);
}

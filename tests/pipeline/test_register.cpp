// Registration: rigid-transform algebra, pairwise estimates on synthetic images with known
// sub-pixel motion, the least-squares chaining, and the stage on the phantom against truth.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <random>

#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "phantom_case.h"
#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/phantom/from_ct.h"
#include "vispack/phantom/phantom.h"
#include "vispack/phantom/score.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/ecc.h"
#include "vispack/pipeline/register/register.h"
#include "vispack/pipeline/register/register_stage.h"

namespace vp = vispack::pipeline;
namespace vph = vispack::phantom;
using vispack::test::bin;
using vispack::test::run_command;
using vispack::test::TempDir;

namespace {

// A textured "body" in uniform gel: smooth random texture (σ = 5 px) inside an ellipse, RGB 8-bit,
// larger than `size` by a margin so warped copies have no empty border.
cv::Mat textured_slice(cv::Size size, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.f, 1.f);
  cv::Mat tex(size, CV_32FC3);
  for (int y = 0; y < size.height; ++y)
    for (int x = 0; x < size.width; ++x)
      tex.at<cv::Vec3f>(y, x) = {noise(rng), noise(rng), noise(rng)};
  cv::GaussianBlur(tex, tex, cv::Size(0, 0), 5.0);
  cv::normalize(tex, tex, 0, 255, cv::NORM_MINMAX);
  cv::Mat body(size, CV_8UC1, cv::Scalar(0));
  cv::ellipse(body, cv::Point(size.width / 2, size.height / 2),
              cv::Size(size.width * 3 / 8, size.height * 3 / 8), 10, 0, 360, cv::Scalar(255), -1);
  cv::Mat out(size, CV_8UC3, cv::Scalar(40, 70, 160));  // blue gel
  cv::Mat tex8;
  tex.convertTo(tex8, CV_8UC3);
  tex8.copyTo(out, body);
  return out;
}

// observed(p) = truth(q) with p = c + R(θ)(q − c) + d, i.e. observed = truth warped forward.
cv::Mat observe(const cv::Mat& truth, const vp::Rigid& t) {
  cv::Mat out;
  cv::warpAffine(truth, out, cv::Mat(vp::rigid_matrix(t, vp::image_centre(truth.size()))),
                 truth.size(), cv::INTER_CUBIC, cv::BORDER_CONSTANT, cv::Scalar(40, 70, 160));
  return out;
}

}  // namespace

TEST(Rigid, MatrixRoundTripsAndScales) {
  const cv::Point2d c = vp::image_centre(256, 192);
  EXPECT_DOUBLE_EQ(c.x, 127.5);
  EXPECT_DOUBLE_EQ(c.y, 95.5);
  vp::Rigid t{3.5, -2.25, 7.75};
  vp::Rigid back = vp::rigid_from_matrix(vp::rigid_matrix(t, c), c);
  EXPECT_NEAR(back.rotation_deg, 3.5, 1e-12);
  EXPECT_NEAR(back.dx_px, -2.25, 1e-12);
  EXPECT_NEAR(back.dy_px, 7.75, 1e-12);
  // The centre maps to c + d.
  cv::Matx23d m = vp::rigid_matrix(t, c);
  EXPECT_NEAR(m(0, 0) * c.x + m(0, 1) * c.y + m(0, 2), c.x - 2.25, 1e-12);
  // Counter-clockwise as displayed with y down: +90° sends (x, y) − c = (1, 0) to (0, 1).
  cv::Matx23d r90 = vp::rigid_matrix({90, 0, 0}, {0, 0});
  EXPECT_NEAR(r90(1, 0), 1.0, 1e-12);
  // scale/unscale invert each other; a pure shift halves at scale 0.5.
  cv::Matx23d s = vp::scale_affine(vp::rigid_matrix({0, 4, -2}, c), 0.5);
  EXPECT_NEAR(s(0, 2), 2.0, 1e-12);
  EXPECT_NEAR(s(1, 2), -1.0, 1e-12);
  cv::Matx23d u = vp::unscale_affine(vp::scale_affine(m, 0.25), 0.25);
  for (int i = 0; i < 6; ++i)
    EXPECT_NEAR(u.val[i], m.val[i], 1e-12);
  // Similarity round trip.
  vp::Similarity sim{0.8, -4.0, 3.0, 1.5};
  vp::Similarity sb =
      vp::similarity_from_matrix(vp::similarity_matrix(sim, {255.5, 255.5}, c), {255.5, 255.5}, c);
  EXPECT_NEAR(sb.scale, 0.8, 1e-12);
  EXPECT_NEAR(sb.rotation_deg, -4.0, 1e-12);
  EXPECT_NEAR(sb.dx_px, 3.0, 1e-12);
  EXPECT_NEAR(sb.dy_px, 1.5, 1e-12);
  EXPECT_NEAR(vp::rigid_motion_px({0, 3, 4}, {256, 192}), 5.0, 1e-12);
}

TEST(Register, ResampleUndoesTheDrift) {
  cv::Mat truth = textured_slice({256, 192}, 1);
  vp::Rigid t{2.0, 5.5, -3.25};
  cv::Mat registered = vp::resample_rigid(observe(truth, t), t, cv::INTER_LINEAR);
  // Compare away from the border (the warped-out corners are filled with gel).
  cv::Rect inner(40, 40, 176, 112);
  cv::Mat diff;
  cv::absdiff(registered(inner), truth(inner), diff);
  // Bilinear resampling of the smooth texture (σ = 3 px blur) after a cubic forward warp:
  // mean error of a few grey levels at most.
  EXPECT_LT(cv::mean(diff)[0], 3.0);
}

// Pairwise estimates on synthetic motion. Tolerance 0.1 px (the docs/GOALS.md §6 goal) and
// 0.02°: ECC at half resolution measures 0.01–0.07 px here; most of that is the bias of the
// bicubic warp that made the synthetic slice (it blurs by an amount that depends on the
// fractional shift), not of the estimator.
struct PairCase {
  vp::Rigid motion;
};
class PairTest : public ::testing::TestWithParam<PairCase> {};

TEST_P(PairTest, RecoversKnownMotion) {
  const vp::Rigid motion = GetParam().motion;
  cv::Mat a = textured_slice({256, 192}, 7);
  cv::Mat b = observe(a, motion);  // slice b is a moved by `motion`: p_b = motion(p_a)
  vp::RegisterOptions options;
  vp::PairEstimate e =
      vp::estimate_pair(vp::prepare_frame(a, options), vp::prepare_frame(b, options), options);
  EXPECT_TRUE(e.ecc_ok);
  EXPECT_GT(e.quality, 0.9);
  EXPECT_NEAR(e.relative.rotation_deg, motion.rotation_deg, 0.02);
  EXPECT_NEAR(e.relative.dx_px, motion.dx_px, 0.1);
  EXPECT_NEAR(e.relative.dy_px, motion.dy_px, 0.1);
}

INSTANTIATE_TEST_SUITE_P(Synthetic, PairTest,
                         ::testing::Values(PairCase{{0.0, 0.3, -0.7}}, PairCase{{0.4, 1.25, 0.5}},
                                           PairCase{{-1.3, -2.6, 3.1}},
                                           PairCase{{7.0, 29.0, -11.5}},  // a block jump
                                           PairCase{{-6.0, -18.25, 22.75}}));

// A dissimilar pair (register/pair.h step 2; docs/BENCHMARKS.md "Register stage: CPU per
// slice"): slice b shows slice a's texture 4 % larger about an off-centre point (as anatomy that
// grows from slice to slice), so no rigid motion matches it. From the identity start its fine
// ECC creeps, inside the reach, for more than 12 iterations after a middle pass under 0.9: that
// start's result is not accepted (the fine pass stops at 10 iterations as a failure) and the
// pair is measured by the full search, as without a start. The same texture moved rigidly with
// 40 % of it replaced by another (as dissimilar by correlation, but a motion ECC converges to)
// is measured from the start.
TEST(Register, DissimilarPairThatKeepsCreepingIsNotMeasured) {
  const cv::Size size(2048, 1216);  // the real size: the fine pass has a middle level first
  auto texture = [&](std::uint64_t seed) {
    cv::Mat t(size, CV_32F);
    cv::RNG(seed).fill(t, cv::RNG::NORMAL, 0.0, 1.0);
    cv::GaussianBlur(t, t, cv::Size(0, 0), 8.0);
    cv::normalize(t, t, 20, 235, cv::NORM_MINMAX);
    return t;
  };
  const cv::Mat base = texture(5), other = texture(6);
  auto grey8 = [](const cv::Mat& f) {
    cv::Mat g;
    f.convertTo(g, CV_8U);
    cv::Mat rgb;
    cv::cvtColor(g, rgb, cv::COLOR_GRAY2RGB);
    return rgb;
  };
  auto moved = [&](double zoom) {
    cv::Mat m = cv::getRotationMatrix2D(cv::Point2f(600.f, 400.f), 0.0, zoom);
    m.at<double>(0, 2) += 6.0;
    m.at<double>(1, 2) -= 4.0;
    cv::Mat out;
    cv::warpAffine(base, out, m, size, cv::INTER_CUBIC, cv::BORDER_REFLECT);
    return out;
  };
  vp::RegisterOptions options;  // phase+ecc, ecc_scale 0.5, 50 iterations
  const vp::RegisterFrame a = vp::prepare_frame(grey8(base), options);
  ASSERT_FALSE(a.middle.empty());
  const vp::Rigid start{0.0, 0.0, 0.0};

  // The premise, the pair's fine ECC by hand (register/pair.h step 2): after the middle pass,
  // at a correlation under 0.9, the fine pass creeps on for more than 12 iterations and ends
  // within the reach (32 px from the start: it would be accepted).
  const vp::RegisterFrame grown = vp::prepare_frame(grey8(moved(1.04)), options);
  vp::EccOptions probe;
  probe.iterations = options.ecc_iterations;
  probe.eps = 1e-5;
  cv::Matx23d w(1, 0, 0, 0, 1, 0);
  const std::optional<double> middle_rho = vp::ecc_euclidean(a.middle, grown.middle, w, probe);
  ASSERT_TRUE(middle_rho.has_value());
  EXPECT_LT(*middle_rho, 0.9);
  const double up = a.fine_scale / a.middle_scale;
  w(0, 2) *= up;
  w(1, 2) *= up;
  int updates = 0;
  probe.diverged = [&](const cv::Matx23d&) { return ++updates < 0; };
  ASSERT_TRUE(vp::ecc_euclidean(a.fine, grown.fine, w, probe).has_value());
  EXPECT_GT(updates, 12);
  EXPECT_LT(std::hypot(w(0, 2), w(1, 2)) / a.fine_scale, 32.0);

  // That start's result is not accepted: the pair is measured by the full search (the coarse
  // search's start, from which the fine pass converges), as without a start.
  const vp::PairEstimate from_start = vp::estimate_pair(a, grown, options, &start);
  const vp::PairEstimate searched = vp::estimate_pair(a, grown, options);
  EXPECT_EQ(from_start.relative.dx_px, searched.relative.dx_px);
  EXPECT_EQ(from_start.relative.dy_px, searched.relative.dy_px);
  EXPECT_EQ(from_start.relative.rotation_deg, searched.relative.rotation_deg);

  // Dissimilar by correlation, but converging: measured, at the true shift.
  const vp::RegisterFrame mixed =
      vp::prepare_frame(grey8(cv::Mat(0.6 * moved(1.0) + 0.4 * other)), options);
  const vp::PairEstimate converging = vp::estimate_pair(a, mixed, options, &start);
  EXPECT_TRUE(converging.ecc_ok);
  EXPECT_LT(converging.quality, 0.9);
  EXPECT_NEAR(converging.relative.dx_px, 6.0, 0.3);
  EXPECT_NEAR(converging.relative.dy_px, -4.0, 0.3);
}

// A dissimilar pair whose middle pass creeps (a correlation under 0.9, still moving at its 10th
// update) is not followed further there: the fine pass starts from that 10th iterate and has 10
// updates (register/pair.cpp refine_fine; docs/BENCHMARKS.md "Register stage: CPU per slice").
// The texture grown 2 %: its middle pass alone goes on past its 10th update.
TEST(Register, DissimilarPairsMiddlePassIsNotFollowedPastItsTenthUpdate) {
  const cv::Size size(2048, 1216);  // the real size: the fine pass has a middle level first
  cv::Mat base(size, CV_32F);
  cv::RNG(5).fill(base, cv::RNG::NORMAL, 0.0, 1.0);
  cv::GaussianBlur(base, base, cv::Size(0, 0), 8.0);
  cv::normalize(base, base, 20, 235, cv::NORM_MINMAX);
  cv::Mat grown;
  cv::Mat zoom = cv::getRotationMatrix2D(cv::Point2f(600.f, 400.f), 0.0, 1.02);
  zoom.at<double>(0, 2) += 6.0;
  zoom.at<double>(1, 2) -= 4.0;
  cv::warpAffine(base, grown, zoom, size, cv::INTER_CUBIC, cv::BORDER_REFLECT);
  auto rgb = [](const cv::Mat& f) {
    cv::Mat g, out;
    f.convertTo(g, CV_8U);
    cv::cvtColor(g, out, cv::COLOR_GRAY2RGB);
    return out;
  };
  vp::RegisterOptions options;  // phase+ecc, ecc_scale 0.5, 50 iterations
  const vp::RegisterFrame a = vp::prepare_frame(rgb(base), options);
  const vp::RegisterFrame b = vp::prepare_frame(rgb(grown), options);
  ASSERT_FALSE(a.middle.empty());
  const cv::Point2d centre = vp::image_centre(size);
  const vp::Rigid start{0.0, 0.0, 0.0};

  // The pair's passes by hand (the options refine_fine gives them): the middle pass from the
  // start, every update's correlation and iterate recorded.
  auto pass = [&](const cv::Mat& from, const cv::Mat& to, double scale, cv::Matx23d& full,
                  int iterations, std::vector<double>& rhos, std::vector<cv::Matx23d>& path) {
    vp::EccOptions o;
    o.iterations = iterations;
    o.eps = 1e-5;
    o.min_step_px = 0.02 * scale;
    o.diverged = [&](const cv::Matx23d& w) {
      path.push_back(vp::unscale_affine(w, scale));
      return false;
    };
    o.give_up = [&](double rho, int) {
      rhos.push_back(rho);
      return false;
    };
    cv::Matx23d w = vp::scale_affine(full, scale);
    const std::optional<double> rho = vp::ecc_euclidean(from, to, w, o);
    full = vp::unscale_affine(w, scale);
    return rho;
  };
  std::vector<double> middle_rhos;
  std::vector<cv::Matx23d> middle_path;
  cv::Matx23d m = vp::rigid_matrix(start, centre);
  ASSERT_TRUE(
      pass(a.middle, b.middle, a.middle_scale, m, options.ecc_iterations, middle_rhos, middle_path)
          .has_value());
  ASSERT_GT(middle_path.size(), 10u);  // the premise: it creeps on
  for (std::size_t i = 9; i < middle_rhos.size(); ++i)
    ASSERT_LT(middle_rhos[i], 0.9) << i;
  // The fine pass from its 10th iterate, 10 updates, converging before the last (else the pair
  // would be a failure and go to the full search).
  std::vector<double> fine_rhos;
  std::vector<cv::Matx23d> fine_path;
  cv::Matx23d fine = middle_path[9];
  const std::optional<double> fine_rho =
      pass(a.fine, b.fine, a.fine_scale, fine, 10, fine_rhos, fine_path);
  ASSERT_TRUE(fine_rho.has_value());
  ASSERT_LT(fine_path.size(), 10u);
  const vp::Rigid by_hand = vp::rigid_from_matrix(fine, centre);

  const vp::PairEstimate est = vp::estimate_pair(a, b, options, &start);
  EXPECT_TRUE(est.ecc_ok);
  EXPECT_NEAR(est.relative.dx_px, by_hand.dx_px, 1e-9);
  EXPECT_NEAR(est.relative.dy_px, by_hand.dy_px, 1e-9);
  EXPECT_NEAR(est.relative.rotation_deg, by_hand.rotation_deg, 1e-9);
  EXPECT_NEAR(est.quality, *fine_rho, 1e-12);
}

TEST(Register, BrightnessChangeDoesNotMoveTheEstimate) {
  cv::Mat a = textured_slice({256, 192}, 3);
  cv::Mat b = observe(a, {0.5, 1.5, -0.5});
  b.convertTo(b, -1, 0.8, 10);  // gain and offset
  vp::RegisterOptions options;
  vp::PairEstimate e =
      vp::estimate_pair(vp::prepare_frame(a, options), vp::prepare_frame(b, options), options);
  EXPECT_NEAR(e.relative.rotation_deg, 0.5, 0.02);
  EXPECT_NEAR(e.relative.dx_px, 1.5, 0.05);
  EXPECT_NEAR(e.relative.dy_px, -0.5, 0.05);
}

TEST(Register, SolveChainIsExactOnConsistentEdges) {
  // Cumulative truth; edges k−1→k and k−2→k computed exactly from it.
  const cv::Point2d c = vp::image_centre(256, 192);
  std::vector<vp::Rigid> truth = {
      {0, 0, 0}, {0.5, 1, 2}, {1.0, -3, 2.5}, {-2, 10, 4}, {-1.5, 9, 5}};
  std::vector<vp::PairEdge> edges;
  for (int k = 1; k < 5; ++k) {
    for (int j = std::max(0, k - 2); j < k; ++j) {
      cv::Matx23d rel = vp::compose_affine(vp::rigid_matrix(truth[k], c),
                                           vp::invert_affine(vp::rigid_matrix(truth[j], c)));
      edges.push_back({j, k, vp::rigid_from_matrix(rel, c), 1.0});
    }
  }
  std::vector<vp::Rigid> solved = vp::solve_chain(5, edges);
  for (int k = 0; k < 5; ++k) {
    EXPECT_NEAR(solved[k].rotation_deg, truth[k].rotation_deg, 1e-6) << k;
    EXPECT_NEAR(solved[k].dx_px, truth[k].dx_px, 1e-6) << k;
    EXPECT_NEAR(solved[k].dy_px, truth[k].dy_px, 1e-6) << k;
  }
  EXPECT_THROW(vp::solve_chain(3, {{0, 5, {}, 1.0}}), vispack::Error);
}

TEST(Register, SkipEdgesAverageOutPairErrors) {
  // Noisy edges (σ = 0.1 px) along a stack of 200 identity slices: the chain with k−2 edges
  // must end closer to the truth than the neighbour-only chain on average over trials.
  std::mt19937 rng(11);
  std::normal_distribution<double> noise(0.0, 0.1);
  double err_chain = 0, err_graph = 0;
  const int n = 200, trials = 20;
  for (int t = 0; t < trials; ++t) {
    std::vector<vp::PairEdge> one, two;
    for (int k = 1; k < n; ++k) {
      vp::PairEdge e{k - 1, k, {0, noise(rng), noise(rng)}, 1.0};
      one.push_back(e);
      two.push_back(e);
      if (k >= 2) two.push_back({k - 2, k, {0, noise(rng), noise(rng)}, 1.0});
    }
    auto a = vp::solve_chain(n, one), b = vp::solve_chain(n, two);
    err_chain += std::hypot(a[n - 1].dx_px, a[n - 1].dy_px);
    err_graph += std::hypot(b[n - 1].dx_px, b[n - 1].dy_px);
  }
  EXPECT_LT(err_graph, 0.85 * err_chain);
}

TEST(Register, ChainFlagsBlackDuplicateAndJump) {
  // Stack of 8 synthetic slices: slice 3 black, slice 5 a duplicate of 4, a jump at slice 6.
  cv::Mat base = textured_slice({256, 192}, 5);
  std::vector<vp::Rigid> truth(8);
  for (int k = 1; k < 8; ++k)
    truth[k] = {0.1 * k, 0.4 * k, -0.3 * k};
  for (int k = 6; k < 8; ++k)
    truth[k].dx_px += 20.0, truth[k].rotation_deg += 4.0;
  truth[5] = truth[4];
  std::vector<cv::Mat> slices(8);
  for (int k = 0; k < 8; ++k)
    slices[k] = observe(base, truth[k]);
  slices[3] = cv::Mat(base.size(), CV_8UC3, cv::Scalar(0, 0, 0));
  slices[5] = slices[4].clone();
  vp::RegisterOptions options;
  auto pairs = vp::compute_pairs(
      0, 8, [&](int k) { return vp::prepare_frame(slices[k], options); }, options, 2);
  ASSERT_EQ(pairs.size(), 8u);
  EXPECT_TRUE(pairs[3].black);
  EXPECT_TRUE(pairs[3].edges.empty());
  ASSERT_TRUE(pairs[5].duplicate_of.has_value());
  EXPECT_EQ(*pairs[5].duplicate_of, 4);
  // Slice 4 reaches back over the black slice 3 to slices 2 and 1.
  ASSERT_EQ(pairs[4].edges.size(), 2u);
  EXPECT_EQ(pairs[4].edges[0].from, 2);
  EXPECT_EQ(pairs[4].edges[1].from, 1);
  auto t = vp::chain_transforms(pairs, base.size(), 6.0);
  for (int k : {1, 2, 4, 5, 6, 7}) {
    EXPECT_NEAR(t[k].rigid.dx_px, truth[k].dx_px, 0.1) << k;
    EXPECT_NEAR(t[k].rigid.dy_px, truth[k].dy_px, 0.1) << k;
    EXPECT_NEAR(t[k].rigid.rotation_deg, truth[k].rotation_deg, 0.03) << k;
  }
  // Black slice 3: halfway between 2 and 4.
  EXPECT_TRUE(t[3].black);
  EXPECT_NEAR(t[3].rigid.dx_px, 0.5 * (truth[2].dx_px + truth[4].dx_px), 0.1);
  for (int k = 0; k < 8; ++k)
    EXPECT_EQ(t[k].jump, k == 6) << k;
  EXPECT_EQ(t[5].duplicate_of.value_or(-1), 4);
  // Pair records survive JSON.
  auto back = vp::slice_pairs_from_json(vp::to_json(pairs[6]), "test");
  ASSERT_EQ(back.edges.size(), pairs[6].edges.size());
  EXPECT_DOUBLE_EQ(back.edges[0].relative.dx_px, pairs[6].edges[0].relative.dx_px);
  EXPECT_EQ(back.pixel_hash, pairs[6].pixel_hash);
  EXPECT_THROW(vp::slice_pairs_from_json(nlohmann::json{{"index", 1}}, "x"), vispack::FormatError);
}

// The stage on the small phantom against truth/transforms.json (docs/GOALS.md §6 goals).
TEST(RegisterStage, SmallPhantomAgainstTruth) {
  TempDir dir("vispack-register");
  vph::PhantomOptions po;
  po.preset = "small";
  po.seed = 2;
  po.quiet = true;
  const vph::PhantomSummary summary = vph::make_phantom(dir.path(), po);
  const vp::Config config = vp::load_config(dir / "config.json");
  vp::StageOptions so;
  so.quiet = true;
  vp::run_register_stage(config, so);
  const vp::StackTransforms got = vp::read_transforms(vp::transforms_path(config));
  const vp::StackTransforms truth = vp::read_transforms(dir / "truth/transforms.json");
  ASSERT_EQ(got.slices.size(), truth.slices.size());
  const int n = int(got.slices.size());
  // Error of slice k: the largest displacement, over the four corners and the centre, between
  // where the estimate and the truth put an output point in the observed slice (a rotation
  // error shows at the corners, which a centre-only error never sees).
  auto error = [&](int k) {
    const auto& a = got.slices[std::size_t(k)];
    const auto& b = truth.slices[std::size_t(k)];
    return vispack::test::max_displacement_px({a.rigid.dx_px, a.rigid.dy_px, a.rigid.rotation_deg},
                                              {b.rigid.dx_px, b.rigid.dy_px, b.rigid.rotation_deg},
                                              got.width, got.height);
  };
  double sum2 = 0, first_q = 0, last_q = 0;
  int counted = 0;
  for (int k = 0; k < n; ++k) {
    EXPECT_EQ(got.slices[std::size_t(k)].black, k == summary.black_slice) << k;
    EXPECT_EQ(got.slices[std::size_t(k)].jump, k == summary.jump_slice) << k;
    if (k == summary.duplicate_slice) {
      EXPECT_EQ(got.slices[std::size_t(k)].duplicate_of.value_or(-1), k - 1);
    }
    if (k == summary.black_slice) continue;
    const double e = error(k);
    sum2 += e * e, ++counted;
    if (k < n / 4) first_q = std::max(first_q, e);
    if (k >= n - n / 4) last_q = std::max(last_q, e);
  }
  const double rms = std::sqrt(sum2 / counted);
  RecordProperty("drift_rms_px", std::to_string(rms));
  // Absolute error against the CT-defined frame (truth in frame "ct"): every slice is anchored
  // on its own CT slice, so this includes what the slice-0-relative measure used to hide.
  // Measured 0.20 px over the corners and centre (rotation error shows at the corners); the
  // 0.1 px goal (docs/GOALS.md §6) is not met yet.
  EXPECT_LE(rms, 0.3);
  // No growth: the last quarter's worst error is within 2× (+0.05 px) of the first quarter's.
  EXPECT_LE(last_q, 2.0 * first_q + 0.05) << "first quarter " << first_q;
  // The output frame is defined by the config, never estimated: ct_to_rgb equals the truth's.
  EXPECT_EQ(got.extra.value("frame", ""), "ct");
  EXPECT_FALSE(got.reference_slice.has_value());
  ASSERT_TRUE(got.ct_to_rgb.has_value());
  ASSERT_TRUE(truth.ct_to_rgb.has_value());
  EXPECT_NEAR(got.ct_to_rgb->scale, truth.ct_to_rgb->scale, 1e-6);  // truth rounded to 1e-6
  EXPECT_NEAR(got.ct_to_rgb->rotation_deg, truth.ct_to_rgb->rotation_deg, 1e-6);
  EXPECT_NEAR(got.ct_to_rgb->dx_px, truth.ct_to_rgb->dx_px, 1e-6);
  EXPECT_NEAR(got.ct_to_rgb->dy_px, truth.ct_to_rgb->dy_px, 1e-6);
  // Every slice with body has an anchor confidence; QC pictures are written.
  for (const auto& s : got.slices) {
    if (!s.black) {
      EXPECT_TRUE(s.extra.contains("anchor_confidence")) << s.index;
    }
  }
  EXPECT_TRUE(std::filesystem::exists(vp::stage_dir(config, "register") + "/qc/transforms.png"));
  EXPECT_TRUE(std::filesystem::exists(vp::stage_dir(config, "register") + "/qc/overlay_0010.png"));
}

namespace {

// Writes phantom `preset` into `dir`, runs the register stage on it and returns its config.
vp::Config register_phantom(const TempDir& dir, const std::string& preset, int seed,
                            int slices = 0) {
  const vp::Config config = vispack::test::make_phantom_case(dir.path(), preset, seed, slices);
  vp::run_register_stage(config, vispack::test::quiet_stage_options());
  return config;
}

}  // namespace

// The anatomy preset (anatomy moving and tapering along z, no fiducials, CT 2× coarser), scored
// by the phantom's own scorer at two stack lengths: the jump found, no false jump, and the
// 0.5 px goal (docs/GOALS.md §6) at both lengths, no growth. Measured 0.34 px (32 slices) and 0.38
// px (64) RMS over the corners and centre.
TEST(RegisterStage, AnatomyPresetDoesNotGrowWithLength) {
  double rms[2] = {0, 0};
  const int lengths[2] = {32, 64};
  for (int i = 0; i < 2; ++i) {
    TempDir dir("vispack-register-anatomy");
    const vp::Config config = register_phantom(dir, "anatomy", 3, lengths[i]);
    const auto truth = vph::read_transforms_file(dir / "truth/transforms.json");
    const auto got = vph::read_transforms_file(vp::transforms_path(config));
    EXPECT_EQ(got.frame, "ct");
    const vph::DriftScore drift = vph::score_drift(truth, got);
    const vph::JumpScore jumps = vph::score_jumps(truth, got);
    EXPECT_EQ(jumps.found, 1) << lengths[i];
    EXPECT_EQ(jumps.false_jumps, 0) << lengths[i];
    rms[i] = drift.rms_px;
    RecordProperty(vispack::cat("drift_rms_px_", lengths[i]), std::to_string(rms[i]));
    EXPECT_LE(rms[i], 0.5) << lengths[i];
  }
  EXPECT_LE(rms[1], rms[0] + 0.1) << "grows with the stack's length";
}

// The anatomy preset at the real slice size (2048×1216, 16 slices spanning the whole body, CT 2×
// coarser): the bodies are large, so the anchors are accurate (0.008° RMS), and the solve must
// not smooth them away (it did: 0.62 px over the body slices before the anchors' σ followed the
// body's size). Scored over the slices whose body covers ≥ 1 % of the frame: measured 0.30 px.
// The first and last slice show no body at all (gel only, in colour and CT): no measurement sees
// their transform, the truth's random walk moved on by ~0.1° (2 px at the corners) from their
// neighbours, and the best prediction is the neighbour's transform (flat): measured 2.2 and
// 0.3 px; asserted within 3 px (a linear extrapolation of the anchors' trend gave 3.4 px).
TEST(RegisterStage, AnatomyVhpPresetAtRealSize) {
  TempDir dir("vispack-register-anatomy-vhp");
  const vp::Config config = register_phantom(dir, "anatomy-vhp", 3);
  const vph::Score score = vph::score_work(dir / "truth", config.work_dir);
  RecordProperty("drift_body_rms_px", std::to_string(score.drift.body_rms_px));
  std::printf("anatomy-vhp: drift rms %.3f px (max %.3f, slice %d); body slices rms %.3f px (%d)\n",
              score.drift.rms_px, score.drift.max_px, score.drift.max_slice,
              score.drift.body_rms_px, score.drift.body_slices);
  EXPECT_EQ(score.drift.body_slices, 14);
  EXPECT_LE(score.drift.body_rms_px, 0.4);
  EXPECT_LE(score.drift.max_px, 3.0);
  EXPECT_EQ(score.jumps.found, 1);
  EXPECT_EQ(score.jumps.false_jumps, 0);
}

// The realistic case: colour slices synthesised from the real head CT (vispack-phantom
// --from-ct: the phantom's own drift, jump, gel, lighting and noise; CT 2× coarser, drift-free),
// the whole stack (108 slices, the top of the head included), scored against its truth. The
// 0.5 px goal of docs/GOALS.md §6 over every slice; measured 0.31 px (0.25 over the 106 slices
// whose body covers ≥ 1 % of the frame), the jump found, no false jump. Skips without the sample
// (scripts/fetch-sample-data.sh head-ct).
TEST(RegisterStage, HeadCtCaseAgainstTruth) {
  const std::string sample = vispack::test::head_ct_sample();
  if (sample.empty())
    GTEST_SKIP() << "head-ct sample not fetched (run scripts/fetch-sample-data.sh head-ct)";
  TempDir dir("vispack-register-head");
  vph::FromCtOptions o;
  o.seed = 2;
  o.quiet = true;
  vph::make_phantom_from_ct(dir.path(), vph::read_ct_volume(sample), o);
  const vp::Config config = vp::load_config(dir / "config.json");
  vp::StageOptions so;
  so.quiet = true;
  vp::run_register_stage(config, so);
  const vph::Score score = vph::score_work(dir / "truth", config.work_dir);
  RecordProperty("drift_rms_px", std::to_string(score.drift.rms_px));
  std::printf("head-CT case: drift rms %.3f px (max %.3f, slice %d); body slices rms %.3f px\n",
              score.drift.rms_px, score.drift.max_px, score.drift.max_slice,
              score.drift.body_rms_px);
  EXPECT_EQ(score.drift.scored, 108);
  EXPECT_LE(score.drift.rms_px, 0.5);
  EXPECT_LE(score.drift.body_rms_px, 0.4);
  EXPECT_EQ(score.jumps.found, 1);
  EXPECT_EQ(score.jumps.false_jumps, 0);
}

// A sharded run (--slices on two halves, then the combining run) gives exactly the unsharded
// result, and every run removes the temporaries a killed earlier run left in its folder.
TEST(RegisterStage, ShardedRunMatchesUnsharded) {
  TempDir dir("vispack-register-shards");
  vph::PhantomOptions po;
  po.preset = "tiny";
  po.seed = 4;
  po.quiet = true;
  const vph::PhantomSummary summary = vph::make_phantom(dir.path(), po);
  ASSERT_GE(summary.slices, 8);
  // Both configs write the full-size registered slices (work.write_registered; off by default),
  // which this test compares. A second config with its own work folder, same inputs.
  nlohmann::json cj = nlohmann::json::parse(vispack::read_file(dir / "config.json"));
  cj["work"]["write_registered"] = true;
  {
    std::ofstream out(dir / "config.json");
    out << cj.dump(1);
  }
  cj["work_dir"] = "work-sharded";
  {
    std::ofstream out(dir / "sharded.json");
    out << cj.dump(1);
  }
  const vp::Config whole = vp::load_config(dir / "config.json");
  const vp::Config sharded = vp::load_config(dir / "sharded.json");
  const std::string reg = bin("vispack-register") + " --quiet --config ";
  std::string out;
  ASSERT_EQ(run_command(reg + (dir / "config.json"), &out), 0) << out;
  const int half = summary.slices / 2;
  const std::string first = vispack::cat(" --slices 0:", half);
  const std::string second = vispack::cat(" --slices ", half, ":", summary.slices);
  ASSERT_EQ(run_command(reg + (dir / "sharded.json") + first, &out), 0) << out;
  // One shard alone cannot chain the stack.
  EXPECT_FALSE(std::filesystem::exists(vp::transforms_path(sharded)));
  ASSERT_EQ(run_command(reg + (dir / "sharded.json") + second, &out), 0) << out;
  // Temporaries of a killed run (AtomicFile names "<final>.tmp-<pid>-<n>").
  const std::string stale_pairs =
      vp::slice_output_path(sharded, "register", "pairs/pairs", 1, "json") + ".tmp-999999-1";
  const std::string stale_rgb = vp::registered_rgb_path(sharded, 2) + ".tmp-999999-2";
  std::filesystem::create_directories(std::filesystem::path(stale_rgb).parent_path());
  std::ofstream(stale_pairs) << "partial";
  std::ofstream(stale_rgb) << "partial";
  // The combining run: reuses every pair record, chains, resamples.
  ASSERT_EQ(run_command(reg + (dir / "sharded.json"), &out), 0) << out;
  EXPECT_FALSE(std::filesystem::exists(stale_pairs));
  EXPECT_FALSE(std::filesystem::exists(stale_rgb));
  const auto report = nlohmann::json::parse(
      vispack::read_file(vp::stage_dir(sharded, "register") + "/report.json"));
  EXPECT_EQ(report.value("pairs_computed", -1), 0) << report.dump();

  const vp::StackTransforms a = vp::read_transforms(vp::transforms_path(whole));
  const vp::StackTransforms b = vp::read_transforms(vp::transforms_path(sharded));
  ASSERT_EQ(a.slices.size(), b.slices.size());
  for (std::size_t k = 0; k < a.slices.size(); ++k) {
    // Same pair records, same solver: equal up to the JSON round trip of doubles.
    EXPECT_NEAR(a.slices[k].rigid.dx_px, b.slices[k].rigid.dx_px, 1e-9) << k;
    EXPECT_NEAR(a.slices[k].rigid.dy_px, b.slices[k].rigid.dy_px, 1e-9) << k;
    EXPECT_NEAR(a.slices[k].rigid.rotation_deg, b.slices[k].rigid.rotation_deg, 1e-9) << k;
    EXPECT_EQ(a.slices[k].jump, b.slices[k].jump) << k;
    EXPECT_EQ(a.slices[k].black, b.slices[k].black) << k;
    EXPECT_EQ(a.slices[k].duplicate_of, b.slices[k].duplicate_of) << k;
    // Registered slices of both halves are written and identical.
    const cv::Mat ra = vp::read_slice(vp::registered_rgb_path(whole, int(k)));
    const cv::Mat rb = vp::read_slice(vp::registered_rgb_path(sharded, int(k)));
    ASSERT_EQ(ra.size(), rb.size()) << k;
    EXPECT_EQ(cv::norm(ra, rb, cv::NORM_INF), 0.0) << k;
  }
  ASSERT_TRUE(a.ct_to_rgb && b.ct_to_rgb);
  EXPECT_NEAR(a.ct_to_rgb->scale, b.ct_to_rgb->scale, 1e-9);
}

TEST(Register, FindsFiducialsToSubPixel) {
  // Gel with a textured body and two tubes of another colour at known sub-pixel centres
  // (anti-aliased discs drawn with 8 fractional bits).
  cv::Mat rgb = textured_slice({512, 384}, 9);
  const cv::Point2d tube_a(40.3, 45.6), tube_b(470.75, 338.2);
  for (const cv::Point2d& c : {tube_a, tube_b})
    cv::circle(rgb, cv::Point(int(std::lround(c.x * 256)), int(std::lround(c.y * 256))), 12 * 256,
               cv::Scalar(72, 176, 84), -1, cv::LINE_AA, 8);
  const std::vector<cv::Point2d> found = vp::find_fiducials(rgb);
  ASSERT_EQ(found.size(), 2u);
  // Sorted by y: tube_a first. Tolerance 0.05 px: the centroid of an anti-aliased disc whose
  // coverage OpenCV rasterises to about 1/16 px.
  EXPECT_NEAR(found[0].x, tube_a.x, 0.05);
  EXPECT_NEAR(found[0].y, tube_a.y, 0.05);
  EXPECT_NEAR(found[1].x, tube_b.x, 0.05);
  EXPECT_NEAR(found[1].y, tube_b.y, 0.05);
  // A tube cut by the frame is not a fiducial (its centroid would be biased).
  cv::circle(rgb, {3, 200}, 12, cv::Scalar(72, 176, 84), -1);
  EXPECT_EQ(vp::find_fiducials(rgb).size(), 2u);
  // No tubes: none.
  EXPECT_TRUE(vp::find_fiducials(textured_slice({512, 384}, 9)).empty());
}

TEST(Register, FiducialsStopTheRandomWalk) {
  // 40 slices whose pair edges all carry the same small error (+0.05 px in x, +0.01°: content
  // that changes along the stack looks like motion), with exact fiducial positions. Pair edges
  // alone drift by ~2 px at the end; with the fiducial group the chain stays on the truth.
  const cv::Size size(256, 192);
  const cv::Point2d c = vp::image_centre(size);
  const int n = 40;
  std::vector<vp::Rigid> truth(n);
  std::mt19937 rng(3);
  std::normal_distribution<double> step(0.0, 1.0);
  for (int k = 1; k < n; ++k)
    truth[k] = {truth[k - 1].rotation_deg + 0.05 * step(rng), truth[k - 1].dx_px + 0.3 * step(rng),
                truth[k - 1].dy_px + 0.3 * step(rng)};
  const std::vector<cv::Point2d> tubes = {{20.0, 25.0}, {235.0, 170.0}};
  std::vector<vp::SlicePairs> pairs(n), plain(n);
  for (int k = 0; k < n; ++k) {
    vp::SlicePairs& p = pairs[std::size_t(k)];
    p.index = k;
    const cv::Matx23d tk = vp::rigid_matrix(truth[k], c);
    for (const auto& q : tubes)
      p.fiducials.push_back(
          {tk(0, 0) * q.x + tk(0, 1) * q.y + tk(0, 2), tk(1, 0) * q.x + tk(1, 1) * q.y + tk(1, 2)});
    for (int j = std::max(0, k - 2); j < k; ++j) {
      vp::Rigid rel = vp::rigid_from_matrix(
          vp::compose_affine(tk, vp::invert_affine(vp::rigid_matrix(truth[j], c))), c);
      rel.dx_px += 0.05 * (k - j);
      rel.rotation_deg += 0.01 * (k - j);
      p.edges.push_back({j, k, rel, 1.0});
    }
    plain[std::size_t(k)] = p;
    plain[std::size_t(k)].fiducials.clear();
  }
  int groups = -1;
  const auto with = vp::chain_transforms(pairs, size, 6.0, &groups);
  const auto without = vp::chain_transforms(plain, size, 6.0);
  EXPECT_EQ(groups, 1);
  double worst_with = 0, worst_without = 0;
  for (int k = 0; k < n; ++k) {
    worst_with = std::max(worst_with, std::hypot(with[k].rigid.dx_px - truth[k].dx_px,
                                                 with[k].rigid.dy_px - truth[k].dy_px));
    worst_without = std::max(worst_without, std::hypot(without[k].rigid.dx_px - truth[k].dx_px,
                                                       without[k].rigid.dy_px - truth[k].dy_px));
  }
  EXPECT_GT(worst_without, 1.5);  // 39 × 0.05 px, plus the rotation error's lever
  // With fiducials: the bias is spread into a small residual (weights 1 : 2), not accumulated;
  // 0.1 px is the docs/GOALS.md drift goal.
  EXPECT_LT(worst_with, 0.1);
}

// The QC overlay of a slice whose pairs the run computed is drawn from the small picture written
// with its record as the slice was read (one decode per slice, no picture held in memory between
// the record and the overlay); with work.write_registered the full-size registered slice is
// decoded, warped and downsampled instead. Both pictures show the same registered slice:
// measured mean difference 0.5 grey levels (small phantom, slice 10).
TEST(RegisterStage, OverlayFromTheKeptPictureMatchesTheFullSizePath) {
  TempDir dir;
  vp::Config config = vispack::test::make_phantom_case(dir.path(), "small", 1, 12);
  const std::string overlay = vp::stage_dir(config, "register") + "/qc/overlay_0010.png";
  auto options = vispack::test::quiet_stage_options();
  options.force = true;
  config.work.write_registered = false;
  vp::run_register_stage(config, options);
  const cv::Mat kept = vp::read_slice(overlay);
  // The unsharded run wrote the picture beside the record that names it.
  const std::string picture = vp::slice_output_path(config, "register", "pairs/picture", 10, "png");
  ASSERT_TRUE(std::filesystem::exists(picture));
  EXPECT_EQ(nlohmann::json::parse(vispack::read_file(vp::slice_output_path(
                                      config, "register", "pairs/pairs", 10, "json")))
                .value("picture", ""),
            vp::file_identity(picture));
  config.work.write_registered = true;
  vp::run_register_stage(config, options);
  const cv::Mat full = vp::read_slice(overlay);
  ASSERT_EQ(kept.size(), full.size());
  ASSERT_EQ(kept.type(), full.type());
  cv::Mat diff;
  cv::absdiff(kept, full, diff);
  EXPECT_LE(cv::mean(diff)[0], 1.5);
  // The slice's drift is undone in both: shifted by one picture pixel they differ far more.
  cv::Mat shifted;
  cv::absdiff(kept(cv::Rect(1, 0, kept.cols - 1, kept.rows)),
              full(cv::Rect(0, 0, full.cols - 1, full.rows)), shifted);
  EXPECT_GT(cv::mean(shifted)[0], 2.0 * cv::mean(diff)[0] + 0.5);
}

// --records-only shards measure their records only, whichever finishes last: none solves or
// draws (a cluster's measure shards then take the same time), and every shard's report says it
// waits. The second pass of a shard solves the whole stack and draws its own range's overlays;
// a shard run without the flag that recomputes its records (--force) solves too.
TEST(RegisterStage, RecordsOnlyShardsMeasureOnly) {
  TempDir dir;
  const vp::Config config = vispack::test::make_phantom_case(dir.path(), "tiny", 3, 12);
  auto options = vispack::test::quiet_stage_options();
  options.records_only = true;
  const std::string qc = vp::stage_dir(config, "register") + "/qc/";
  const std::string reports = vp::stage_dir(config, "register") + "/report-";
  for (const auto& [range, report] : {std::pair{"0:6", "0-6"}, std::pair{"6:12", "6-12"}}) {
    options.slices = range;
    vp::run_register_stage(config, options);
    const auto j = nlohmann::json::parse(vispack::read_file(reports + report + ".json"));
    EXPECT_EQ(j.value("pairs_computed", -1), 6) << range;
    EXPECT_NE(j.value("waiting", "").find("6 pair records measured"), std::string::npos)
        << range << ": " << j.dump();
  }
  EXPECT_FALSE(std::filesystem::exists(vp::transforms_path(config)));
  EXPECT_FALSE(std::filesystem::exists(qc + "overlay_0000.png"));
  EXPECT_FALSE(std::filesystem::exists(qc + "overlay_0011.png"));
  // The second pass of shard 6:12: every record present, none computed: solves and draws 6..11.
  options.records_only = false;
  vp::run_register_stage(config, options);
  const auto j = nlohmann::json::parse(vispack::read_file(reports + "6-12.json"));
  EXPECT_EQ(j.value("pairs_computed", -1), 0);
  EXPECT_FALSE(j.contains("waiting")) << j.dump();
  EXPECT_TRUE(std::filesystem::exists(vp::transforms_path(config)));
  EXPECT_TRUE(std::filesystem::exists(qc + "overlay_0011.png"));
  EXPECT_FALSE(std::filesystem::exists(qc + "overlay_0000.png"));
  std::filesystem::remove(vp::transforms_path(config));
  options.slices = "0:6";
  options.force = true;
  vp::run_register_stage(config, options);
  EXPECT_TRUE(std::filesystem::exists(vp::transforms_path(config)));
  EXPECT_TRUE(std::filesystem::exists(qc + "overlay_0000.png"));
}

// A sharded run keeps each slice's overlay picture with its pair record; the shard run after the
// solve (a cluster's per-slice job, another process) draws the QC overlay from it, without
// decoding the full-size slice: slice 3's file is overwritten with garbage of the same size and
// mtime (its identity, so its record stays valid) and the overlay is still drawn, byte-identical
// to the one an unsharded run draws from its own recorded picture. A picture that is not the one
// recorded (rewritten: new identity) is not used: the run decodes the slice and fails on it.
TEST(RegisterStage, ShardDrawsTheOverlayFromTheRecordedPicture) {
  TempDir whole_dir, dir;
  const vp::Config whole = vispack::test::make_phantom_case(whole_dir.path(), "tiny", 3, 12);
  const vp::Config config = vispack::test::make_phantom_case(dir.path(), "tiny", 3, 12);
  auto options = vispack::test::quiet_stage_options();
  vp::run_register_stage(whole, options);
  for (const char* range : {"0:6", "6:12", "0:0"}) {
    options.slices = range;
    vp::run_register_stage(config, options);
  }
  const std::string picture = vp::slice_output_path(config, "register", "pairs/picture", 3, "png");
  ASSERT_TRUE(std::filesystem::exists(picture));
  const std::string overlay = vp::stage_dir(config, "register") + "/qc/overlay_0003.png";
  std::filesystem::remove(overlay);
  const std::string slice = vp::stack_slices(config)[3].path;
  const auto mtime = std::filesystem::last_write_time(slice);
  const std::string original = vispack::read_file(slice);
  vispack::write_file_atomic(slice, std::string(original.size(), 'x'));
  std::filesystem::last_write_time(slice, mtime);
  options.slices = "0:6";
  vp::run_register_stage(config, options);
  ASSERT_TRUE(std::filesystem::exists(overlay));
  EXPECT_EQ(vispack::read_file(overlay),
            vispack::read_file(vp::stage_dir(whole, "register") + "/qc/overlay_0003.png"));
  // The picture rewritten (same pixels, new identity): no longer the recorded one.
  vispack::write_file_atomic(picture, vispack::read_file(picture));
  std::filesystem::remove(overlay);
  EXPECT_THROW(vp::run_register_stage(config, options), vispack::InputError);
}

// The `tiny` phantom (96×64, 24 slices, CT 2× coarser: the quick benchmark's stack, seed 1, and
// seed 3), scored against its truth: over the truth body, docs/GOALS.md §6's cumulative error
// for CT 2× coarser, ≤ 0.5 px RMS (measured 0.26 px, seed 1; 0.20, seed 3), the jump found and no
// false one. The frame's RMS (corners and centre; 0.50 / 0.38 px) is not bounded here: seed 1's
// 0.504 px is over that goal by its corners' lever on the anchors' common bias (docs/BENCHMARKS.md,
// "Registration anchored on the CT", the `tiny` rows).
TEST(RegisterStage, TinyPhantomDriftOverTheBodyWithinTheGoal) {
  for (int seed : {1, 3}) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    TempDir dir("vispack-tiny-drift");
    const vp::Config config = vispack::test::make_phantom_case(dir.path(), "tiny", seed);
    vp::run_register_stage(config, vispack::test::quiet_stage_options());
    const vph::Score score = vph::score_work(dir / "truth", config.work_dir);
    std::printf("tiny, seed %d: drift rms %.3f px (max %.3f), over the body %.3f px (max %.3f)\n",
                seed, score.drift.rms_px, score.drift.max_px, score.drift.over_body_rms_px,
                score.drift.over_body_max_px);
    EXPECT_EQ(score.drift.scored, 24);
    EXPECT_LE(score.drift.over_body_rms_px, 0.5);
    EXPECT_EQ(score.jumps.found, 1);
    EXPECT_EQ(score.jumps.false_jumps, 0);
  }
}

// A block jump smaller than register.jump_px (3..6 px, with its 2..4° rotation): the two anchors
// and the pair between them agree on the step, so the walk prior is cut there instead of
// spreading the step over the stack (docs/ARCHITECTURE.md, "Registration"; BENCHMARKS
// "Registration when the drift is not the solver's prior"). Without that cut this case scored
// 2.1 px RMS over the body and missed the jump.
TEST(RegisterStage, SmallBlockJumpUnderTheThresholdIsNotSmoothedAway) {
  TempDir dir("vispack-small-jump");
  vph::PhantomOptions options;
  options.preset = "small";
  options.seed = 3;
  options.jump_px_min = 3;
  options.jump_px_max = 6;
  options.defects = false;
  options.quiet = true;
  vph::make_phantom(dir.path(), options);
  const vispack::pipeline::Config config = vispack::pipeline::load_config(dir / "config.json");
  vispack::pipeline::run_register_stage(config, vispack::test::quiet_stage_options());
  const vph::Score score = vph::score_work(dir / "truth", config.work_dir);
  std::printf("small block jump: drift over the body %.3f px RMS, max %.3f px; jumps %d of %d\n",
              score.drift.over_body_rms_px, score.drift.over_body_max_px, score.jumps.found,
              score.jumps.true_jumps);
  EXPECT_LE(score.drift.over_body_rms_px, 0.3);
  EXPECT_LE(score.drift.over_body_max_px, 0.5);
  EXPECT_EQ(score.jumps.found, 1);
  EXPECT_EQ(score.jumps.false_jumps, 0);
}

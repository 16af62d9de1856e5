// The scoring library (score.h) against hand-computed cases, and end to end on a work folder made
// from the truth itself (perfect) and then spoiled by known amounts.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/nrrd.h"
#include "vispack/phantom/phantom.h"
#include "vispack/phantom/score.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vph = vispack::phantom;
namespace fs = std::filesystem;
using nlohmann::json;
using vispack::test::bin;
using vispack::test::run_command;
using vispack::test::TempDir;

namespace {

vph::TransformsFile stack(int w, int h, std::vector<vph::SliceRigid> t) {
  vph::TransformsFile f;
  f.width = w, f.height = h;
  for (const auto& r : t) {
    vph::TransformsFile::Slice s;
    s.t = r;
    f.slices.push_back(s);
  }
  return f;
}

vispack::NrrdVolume volume(vispack::NrrdType type, int w, int h, int n) {
  vispack::NrrdVolume v;
  v.type = type;
  v.dims = {w, h, n};
  v.data.assign(v.byte_size(), 0);
  return v;
}

}  // namespace

TEST(Score, TransformErrorHandComputed) {
  // A pure shift moves every point by its length.
  EXPECT_NEAR(vph::transform_error_px({0, 3, 4}, {0, 0, 0}, 101, 51), 5.0, 1e-12);
  // A rotation θ about c moves the farthest corner by 2 r sin(θ/2); r = |(50, 25)| here.
  EXPECT_NEAR(vph::transform_error_px({1.0, 0, 0}, {0, 0, 0}, 101, 51),
              2 * std::hypot(50.0, 25.0) * std::sin(0.5 * M_PI / 180), 1e-9);
  // 3×3 grid, c = (1, 1), 90° and shift (1, 0): corner (0,0) → (3,0) (3 px), (2,0) → (3,2),
  // (0,2) → (1,0) (√5 each), (2,2) → (1,2) and the centre → (2,1) (1 px): the largest is 3.
  EXPECT_NEAR(vph::transform_error_px({90, 1, 0}, {0, 0, 0}, 3, 3), 3.0, 1e-9);
  // Symmetric in its arguments.
  EXPECT_NEAR(vph::transform_error_px({0, 0, 0}, {90, 1, 0}, 3, 3), 3.0, 1e-9);
  // 5×3 grid, c = (2, 1): a = 90° about c, b = shift (1, 1). R(90°)(x, y) = (−y, x), so corner
  // (0,0) → a (3,−1), b (1,1): √8; (4,0) → a (3,3), b (5,1): √8; (0,2) → a (1,−1), b (1,3): 4;
  // (4,2) → a (1,3), b (5,3): 4; centre → a (2,1), b (3,2): √2. The largest is 4. (With the
  // rotation's sign flipped it would be √20 = 4.47: the convention is pinned down.)
  EXPECT_NEAR(vph::transform_error_px({90, 0, 0}, {0, 1, 1}, 5, 3), 4.0, 1e-9);
}

TEST(Score, RelativeTransformComposes) {
  // Shifts only: the difference.
  const vph::SliceRigid r = vph::relative_to({0, 5, -2}, {0, 1, 3}, 64, 48);
  EXPECT_NEAR(r.dx_px, 4, 1e-12);
  EXPECT_NEAR(r.dy_px, -5, 1e-12);
  // With rotations: rel ∘ T_r = T_k, i.e. rel is exactly T_k ∘ T_r⁻¹ (zero error after composing).
  const vph::SliceRigid tk{10, 5, -2}, tr{4, 1, 3};
  const vph::SliceRigid rel = vph::relative_to(tk, tr, 64, 48);
  EXPECT_NEAR(rel.rotation_deg, 6, 1e-12);
  const double cx = 31.5, cy = 23.5;
  auto apply = [&](const vph::SliceRigid& t, double x, double y) {
    const double th = t.rotation_deg * M_PI / 180, c = std::cos(th), s = std::sin(th);
    return cv::Point2d(cx + c * (x - cx) - s * (y - cy) + t.dx_px,
                       cy + s * (x - cx) + c * (y - cy) + t.dy_px);
  };
  for (const cv::Point2d q : {cv::Point2d(0, 0), cv::Point2d(63, 47), cv::Point2d(10, 40)}) {
    const cv::Point2d via_r = apply(tr, q.x, q.y);
    const cv::Point2d composed = apply(rel, via_r.x, via_r.y);
    const cv::Point2d direct = apply(tk, q.x, q.y);
    EXPECT_NEAR(composed.x, direct.x, 1e-9);
    EXPECT_NEAR(composed.y, direct.y, 1e-9);
  }
}

TEST(Score, DriftAndJumps) {
  vph::TransformsFile truth = stack(64, 48, {{1, 2, 3}, {1, 2.5, 3}, {1, 3, 3}, {1, 9, 3}});
  vph::TransformsFile est = truth;
  est.slices[1].t.dx_px += 0.3, est.slices[1].t.dy_px += 0.4;  // 0.5 px off
  est.slices[2].t.dx_px += 100;                                // a lost slice: not scored
  truth.slices[2].black = true;
  truth.slices[3].jump = true;
  est.slices[3].jump = true;
  est.slices[1].jump = true;  // a false jump
  const vph::DriftScore d = vph::score_drift(truth, est);
  ASSERT_EQ(d.error_px.size(), 4u);
  EXPECT_NEAR(d.error_px[0], 0, 1e-12);
  EXPECT_NEAR(d.error_px[1], 0.5, 1e-9);
  EXPECT_TRUE(std::isnan(d.error_px[2]));
  EXPECT_EQ(d.scored, 3);
  EXPECT_NEAR(d.rms_px, std::sqrt(0.25 / 3), 1e-9);
  EXPECT_NEAR(d.max_px, 0.5, 1e-9);
  EXPECT_EQ(d.max_slice, 1);
  // Relative to slice 0 the same (slice 0 is exact).
  EXPECT_NEAR(d.relative_rms_px, d.rms_px, 1e-9);
  // A constant offset of the whole estimate: large absolute error, none relative to slice 0.
  vph::TransformsFile moved = truth;
  for (auto& s : moved.slices)
    s.t.dx_px += 10;
  const vph::DriftScore m = vph::score_drift(truth, moved);
  EXPECT_NEAR(m.rms_px, 10, 1e-9);
  EXPECT_NEAR(m.relative_rms_px, 0, 1e-9);

  const vph::JumpScore j = vph::score_jumps(truth, est);
  EXPECT_EQ(j.true_jumps, 1);
  EXPECT_EQ(j.found, 1);
  EXPECT_EQ(j.missed, 0);
  EXPECT_EQ(j.false_jumps, 1);
  ASSERT_EQ(j.false_slices.size(), 1u);
  EXPECT_EQ(j.false_slices[0], 1);
  // Mismatched stacks are an error, not a silent partial score.
  vph::TransformsFile short_est = est;
  short_est.slices.pop_back();
  EXPECT_THROW(vph::score_drift(truth, short_est), vispack::Error);
}

TEST(Score, MaskIouHandComputed) {
  vispack::NrrdVolume truth = volume(vispack::NrrdType::kUint8, 10, 10, 3);
  std::vector<cv::Mat> est(3);
  // Slice 0: a 4×5 block; the estimate is the same block one pixel to the right:
  // intersection 4×4 = 16, union 24.
  cv::Mat t0(10, 10, CV_8UC1, truth.as<std::uint8_t>());
  t0(cv::Rect(2, 3, 5, 4)).setTo(1);
  est[0] = cv::Mat::zeros(10, 10, CV_8UC1);
  est[0](cv::Rect(3, 3, 5, 4)).setTo(255);
  // Slice 1: both empty (undefined IoU). Slice 2: truth 0.5 % body (not a body slice) found.
  est[1] = cv::Mat::zeros(10, 10, CV_8UC1);
  est[2] = cv::Mat::zeros(10, 10, CV_8UC1);
  const vph::MaskScore m = vph::score_masks(truth, est);
  EXPECT_NEAR(m.iou[0], 16.0 / 24.0, 1e-12);
  EXPECT_TRUE(std::isnan(m.iou[1]));
  EXPECT_TRUE(std::isnan(m.iou[2]));
  EXPECT_NEAR(m.stack_iou, 16.0 / 24.0, 1e-12);
  EXPECT_EQ(m.body_slices, 1);
  EXPECT_NEAR(m.mean_body_iou, 16.0 / 24.0, 1e-12);
  EXPECT_EQ(m.min_body_slice, 0);
  est[2].at<std::uint8_t>(0, 0) = 1;  // one false pixel where the truth is empty: IoU 0
  EXPECT_NEAR(vph::score_masks(truth, est).iou[2], 0.0, 1e-12);
  EXPECT_NEAR(vph::score_masks(truth, est).stack_iou, 16.0 / 25.0, 1e-12);
}

TEST(Score, LabelsAwayFromEdgesHandComputed) {
  // 12×12: label 1 for x < 6, label 2 for x ≥ 6. With edge_px 2 (5×5 windows, edges
  // replicated) the uniform columns are x 0..3 and 8..11: 8 × 12 = 96 pixels counted.
  vispack::NrrdVolume truth = volume(vispack::NrrdType::kUint16, 12, 12, 2);
  for (int k = 0; k < 2; ++k) {
    cv::Mat t(12, 12, CV_16UC1, truth.as<std::uint16_t>() + 144 * k);
    t.colRange(0, 6).setTo(1);
    t.colRange(6, 12).setTo(2);
  }
  std::vector<cv::Mat> est(2);
  est[0] = cv::Mat(12, 12, CV_16UC1, truth.as<std::uint16_t>()).clone();
  est[0].at<std::uint16_t>(1, 1) = 3;         // counted and wrong
  est[0].at<std::uint16_t>(6, 6) = 3;         // next to the class edge: not counted
  est[1] = cv::Mat::zeros(12, 12, CV_16UC1);  // slice 1 excluded (say, lost)
  const vph::LabelScore l = vph::score_labels(truth, est, {1}, 2);
  EXPECT_EQ(l.counted, 96u);
  EXPECT_EQ(l.equal, 95u);
  EXPECT_NEAR(l.overall, 95.0 / 96.0, 1e-12);
  EXPECT_NEAR(l.accuracy[0], 95.0 / 96.0, 1e-12);
  EXPECT_TRUE(std::isnan(l.accuracy[1]));
  EXPECT_EQ(l.scored_slices, 1);
  // Not excluded, the all-zero slice 1 counts 96 wrong pixels.
  const vph::LabelScore all = vph::score_labels(truth, est, {}, 2);
  EXPECT_EQ(all.counted, 192u);
  EXPECT_EQ(all.equal, 95u);
  EXPECT_EQ(all.worst_slice, 1);
}

// End to end: a work folder made from the truth scores perfectly; spoiled by known amounts it
// scores exactly those amounts; vispack-score prints the same numbers as JSON.
TEST(Score, WorkFolderFromTruthThenSpoiled) {
  TempDir dir("vispack-score");
  vph::PhantomOptions po;
  po.preset = "tiny";
  po.seed = 5;
  po.slices = 10;
  po.defects = true;
  po.quiet = true;
  const vph::PhantomSummary summary = vph::make_phantom(dir.path(), po);
  const std::string truth = dir / "truth", work = dir / "work";
  fs::create_directories(work + "/register");
  fs::create_directories(work + "/mask");
  fs::create_directories(work + "/labels");
  json t = json::parse(vispack::read_file(truth + "/transforms.json"));
  const vispack::NrrdVolume mask = vispack::read_nrrd(truth + "/mask.nrrd");
  const vispack::NrrdVolume labels = vispack::read_nrrd(truth + "/labels.nrrd");
  const int W = 96, H = 64, N = 10;
  auto write_work = [&](const json& transforms) {
    vispack::write_file_atomic(work + "/register/transforms.json", transforms.dump());
    for (int k = 0; k < N; ++k) {
      char name[64];
      std::snprintf(name, sizeof name, "%04d.png", k);
      cv::Mat m(H, W, CV_8UC1, const_cast<std::uint8_t*>(mask.as<std::uint8_t>()) + W * H * k);
      vispack::pipeline::write_image(work + "/mask/mask_" + name, m * 255);
      cv::Mat l(H, W, CV_16UC1, const_cast<std::uint16_t*>(labels.as<std::uint16_t>()) + W * H * k);
      vispack::pipeline::write_image(work + "/labels/labels_" + name, l);
    }
  };
  write_work(t);
  vph::Score s = vph::score_work(truth, work);
  EXPECT_EQ(s.truth_frame, "ct");
  EXPECT_EQ(s.estimate_frame, "ct");
  EXPECT_NEAR(s.drift.rms_px, 0, 1e-5);  // JSON keeps 6 decimals
  EXPECT_EQ(s.drift.scored, N - 2);      // the black and the duplicated slice are not scored
  EXPECT_EQ(s.jumps.true_jumps, 1);
  EXPECT_EQ(s.jumps.found, 1);
  EXPECT_EQ(s.jumps.false_jumps, 0);
  ASSERT_TRUE(s.has_mask);
  EXPECT_DOUBLE_EQ(s.mask.stack_iou, 1.0);
  ASSERT_TRUE(s.has_labels);
  EXPECT_DOUBLE_EQ(s.labels.overall, 1.0);
  EXPECT_GT(s.labels.counted, 1000u);

  // Spoil slice 3 by a 3-4-5 shift, drop the jump flag: exactly 5 px there, jump missed.
  const int k = summary.jump_slice == 3 ? 2 : 3;
  json spoiled = t;
  spoiled["slices"][k]["dx_px"] = double(t["slices"][k]["dx_px"]) + 3;
  spoiled["slices"][k]["dy_px"] = double(t["slices"][k]["dy_px"]) + 4;
  spoiled["slices"][summary.jump_slice]["jump"] = false;
  write_work(spoiled);
  s = vph::score_work(truth, work);
  EXPECT_NEAR(s.drift.error_px[std::size_t(k)], 5.0, 1e-5);
  EXPECT_NEAR(s.drift.max_px, 5.0, 1e-5);
  EXPECT_EQ(s.drift.max_slice, k);
  // Every scored slice of tiny has a body: the body-only RMS is the same 5 px over 8 slices.
  EXPECT_EQ(s.drift.body_slices, N - 2);
  EXPECT_NEAR(s.drift.body_rms_px, 5.0 / std::sqrt(N - 2.0), 1e-5);
  EXPECT_EQ(s.jumps.missed, 1);

  std::string out;
  ASSERT_EQ(
      run_command(bin("vispack-score") + " --json --truth " + truth + " --work " + work, &out), 0)
      << out;
  const json j = json::parse(out);
  EXPECT_NEAR(double(j["drift"]["max_px"]), 5.0, 1e-5);
  EXPECT_EQ(j["jumps"]["missed"], 1);
  EXPECT_DOUBLE_EQ(double(j["mask"]["stack_iou"]), 1.0);
  // A missing work folder is an error naming the file (exit 3).
  EXPECT_EQ(
      run_command(bin("vispack-score") + " --truth " + truth + " --work " + (dir / "nope"), &out),
      3)
      << out;
  EXPECT_NE(out.find("transforms.json"), std::string::npos) << out;
}

// Drift over the body (score.h): a rotation about the frame's centre moves a point at distance r
// by 2r·sin(θ/2), so a small body at the centre shows little of what the corners show; a shift
// moves every point alike; no point, no error.
TEST(Score, DriftOverTheBodyIsTheLargestMoveOverItsPoints) {
  const int W = 201, H = 101;  // centre (100, 50)
  const vph::SliceRigid none{0, 0, 0}, turned{2.0, 0, 0}, shifted{0, 3, -4};
  const double k = 2 * std::sin(1.0 * 3.14159265358979323846 / 180.0);  // 2·sin(θ/2), θ = 2°
  const std::vector<cv::Point> near_centre = {{95, 50}, {110, 50}, {100, 45}};
  EXPECT_NEAR(vph::transform_error_over_px(turned, none, W, H, near_centre), 10 * k, 1e-9);
  EXPECT_NEAR(vph::transform_error_px(turned, none, W, H), std::hypot(100.0, 50.0) * k, 1e-9);
  EXPECT_NEAR(vph::transform_error_over_px(shifted, none, W, H, near_centre), 5.0, 1e-9);
  EXPECT_EQ(vph::transform_error_over_px(turned, none, W, H, {}), 0.0);
}

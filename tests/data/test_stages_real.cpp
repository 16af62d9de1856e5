// Real-data accuracy of the register and mask stages run as a user runs them (docs/GOALS.md §6),
// through build/bin/vispack-register / vispack-mask when they exist, else the stage functions they
// wrap (core/stage_run.h): the head CT's mask excludes the head-holder arc on every slice; the
// Visible Woman stack's known shifts are recovered and its gel is removed by the colour refinement,
// checked against hand-set bounds.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "samples.h"
#include "test_support.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/mask/mask.h"
#include "vispack/pipeline/mask/mask_stage.h"
#include "vispack/pipeline/register/register.h"
#include "vispack/pipeline/register/register_stage.h"

namespace vispack::test {
namespace {

using pipeline::StageOptions;

// Runs stage `name` ("register", "mask") on the config at `path`: through build/bin/vispack-<name>
// when CMake found that executable (VISPACK_HAVE_<NAME>_EXE), else in-process through the
// library function the executable wraps. Fails the test on a non-zero exit.
void run_stage(const std::string& name, const std::string& path) {
  bool have_exe = false;
#ifdef VISPACK_HAVE_REGISTER_EXE
  have_exe |= name == "register";
#endif
#ifdef VISPACK_HAVE_MASK_EXE
  have_exe |= name == "mask";
#endif
  if (have_exe) {
    std::string out;
    int rc = run_command(bin("vispack-" + name) + " --config " + path + " --quiet", &out);
    ASSERT_EQ(rc, 0) << "vispack-" << name << ": " << out;
    return;
  }
  auto config = pipeline::load_config(path);
  StageOptions options;
  options.quiet = true;
  if (name == "register") {
    pipeline::run_register_stage(config, options);
  } else if (name == "mask") {
    pipeline::run_mask_stage(config, options);
  } else {
    FAIL() << "unknown stage " << name;
  }
}

TEST(HeadCtStages, MaskExcludesHeadHolderArcOnEverySlice) {
  VISPACK_REQUIRE_SAMPLE("head-ct");
  TempDir dir("vispack-head-ct-stages");
  const std::string path = write_sample_config("head-ct", dir.path());
  auto config = pipeline::load_config(path);
  ASSERT_NO_FATAL_FAILURE(run_stage("register", path));
  ASSERT_NO_FATAL_FAILURE(run_stage("mask", path));

  auto transforms = pipeline::read_transforms(pipeline::transforms_path(config));
  ASSERT_TRUE(transforms.ct_to_rgb.has_value());
  // The colour input is a rendering of the CT itself: the alignment must stay the identity
  // (ct_to_rgb is defined by the config: scale 1 = equal pixel sizes, output_frame identity).
  std::printf("head-ct ct_to_rgb: scale %.4f rot %.3f shift (%.3f, %.3f)\n",
              transforms.ct_to_rgb->scale, transforms.ct_to_rgb->rotation_deg,
              transforms.ct_to_rgb->dx_px, transforms.ct_to_rgb->dy_px);
  EXPECT_NEAR(transforms.ct_to_rgb->scale, 1.0, 0.02);
  EXPECT_NEAR(transforms.ct_to_rgb->dx_px, 0.0, 1.0);
  EXPECT_NEAR(transforms.ct_to_rgb->dy_px, 0.0, 1.0);

  auto hu = read_head_ct_hu();
  ASSERT_EQ(hu.size(), 108u);
  double coverage_sum = 0, worst_bone = 0;
  for (int z = 0; z < 108; ++z) {
    cv::Mat mask = pipeline::read_slice(pipeline::mask_path(config, z));
    ASSERT_EQ(mask.type(), CV_8UC1);
    ASSERT_EQ(mask.size(), cv::Size(256, 256));
    int arc = 0, arc_in_mask = 0;
    for (int y = 0; y <= kArcMaxRow; ++y)
      for (int x = 0; x < 256; ++x)
        if (in_head_holder_band(x, y) && hu[z].at<short>(y, x) > 0) {
          ++arc;
          if (mask.at<uchar>(y, x)) ++arc_in_mask;
        }
    EXPECT_EQ(arc_in_mask, 0) << "slice " << z << ": " << arc_in_mask << " of " << arc
                              << " head-holder pixels are in the mask";
    if (z >= 20 && z <= 80) {  // brain centre is body in the mid slices
      EXPECT_EQ(cv::countNonZero(mask(cv::Rect(118, 100, 20, 20))), 400) << "slice " << z;
    }
    // The bone (> 300 HU, outside the arc band) belongs to the head: the mask keeps it. Thin
    // bone rims of the mastoid air cells, which open to the outside through the ear canal, may
    // be opened away: measured worst 0.12 % (6 px in slice 21); allow 1 %.
    cv::Mat bone = hu[z] > 300, outside = ~mask;
    for (int y = 0; y <= kArcMaxRow; ++y)
      for (int x = 0; x < 256; ++x)
        if (in_head_holder_band(x, y)) bone.at<uchar>(y, x) = 0;
    int bone_px = cv::countNonZero(bone), bone_out = cv::countNonZero(bone & outside);
    worst_bone = std::max(worst_bone, bone_px ? double(bone_out) / bone_px : 0.0);
    EXPECT_LE(bone_out, 0.01 * bone_px)
        << "slice " << z << ": " << bone_out << " of " << bone_px << " bone pixels left out";
    coverage_sum += cv::countNonZero(mask) / 65536.0;
  }
  std::printf("head-ct mean mask coverage %.4f, worst fraction of bone left out %.4f\n",
              coverage_sum / 108, worst_bone);
}

TEST(VisibleWomanStages, ShiftsRecoveredAndGelRemoved) {
  VISPACK_REQUIRE_SAMPLE("visible-woman");
  TempDir dir("vispack-visible-woman-stages");
  const std::string path = write_sample_config("visible-woman", dir.path());
  auto config = pipeline::load_config(path);
  ASSERT_NO_FATAL_FAILURE(run_stage("register", path));
  ASSERT_NO_FATAL_FAILURE(run_stage("mask", path));

  // Registration: the copies are the original shifted by whole pixels (truth/transforms.json).
  auto got = pipeline::read_transforms(pipeline::transforms_path(config));
  std::ifstream in(sample_dir("visible-woman") + "/truth/transforms.json");
  auto truth = nlohmann::json::parse(in);
  ASSERT_EQ(got.slices.size(), truth["slices"].size());
  for (std::size_t k = 0; k < got.slices.size(); ++k) {
    double dx = truth["slices"][k]["dx_px"], dy = truth["slices"][k]["dy_px"];
    std::printf("visible-woman slice %zu: shift (%.3f, %.3f) px, %.3f deg; truth (%g, %g)\n", k,
                got.slices[k].rigid.dx_px, got.slices[k].rigid.dy_px,
                got.slices[k].rigid.rotation_deg, dx, dy);
    // docs/GOALS.md asks 0.1 px RMS on the phantom; a pure shift of identical content is easier.
    EXPECT_NEAR(got.slices[k].rigid.dx_px, dx, 0.1) << "slice " << k;
    EXPECT_NEAR(got.slices[k].rigid.dy_px, dy, 0.1) << "slice " << k;
    EXPECT_NEAR(got.slices[k].rigid.rotation_deg, 0.0, 0.1) << "slice " << k;
    if (k > 0) {  // a jump is a slice-to-slice motion above register.jump_px
      double pdx = truth["slices"][k - 1]["dx_px"], pdy = truth["slices"][k - 1]["dy_px"];
      bool jump = std::hypot(dx - pdx, dy - pdy) > config.registration.jump_px;
      EXPECT_EQ(got.slices[k].jump, jump) << "slice " << k;
    }
  }

  // Mask on the output grid (= the original slice's grid): hand-set bounds, every slice.
  for (int k = 0; k < int(got.slices.size()); ++k) {
    cv::Mat m = pipeline::read_slice(pipeline::mask_path(config, k));
    ASSERT_EQ(m.size(), cv::Size(142, 167));
    const Box in_box = kVwInside;
    cv::Rect inside(in_box.x0, in_box.y0, in_box.x1 - in_box.x0 + 1, in_box.y1 - in_box.y0 + 1);
    EXPECT_EQ(cv::countNonZero(m(inside)), inside.area()) << "slice " << k << ": brain box";
    for (const Box& b : kVwGel) {
      cv::Rect r(b.x0, b.y0, b.x1 - b.x0 + 1, b.y1 - b.y0 + 1);
      EXPECT_EQ(cv::countNonZero(m(r)), 0) << "slice " << k << ": gel box " << r;
    }
  }
}

}  // namespace
}  // namespace vispack::test

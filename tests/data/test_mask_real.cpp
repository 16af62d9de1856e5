// Real-data accuracy of the body mask (docs/GOALS.md §6): the head CT's mask excludes the
// head-holder arc; the Visible Woman slice's gel is removed by the colour refinement, checked
// against hand-set bounds (docs/SAMPLES.md, tests/data/samples.h).
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>

#include <opencv2/core.hpp>

#include "samples.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/mask/mask.h"

namespace vispack::test {
namespace {

// Pixels of the head-holder band with HU > 0 (the arc itself) in one CT slice.
cv::Mat arc_pixels(const cv::Mat& hu) {
  cv::Mat arc(hu.size(), CV_8U, cv::Scalar(0));
  for (int y = 0; y <= kArcMaxRow && y < hu.rows; ++y)
    for (int x = 0; x < hu.cols; ++x)
      if (in_head_holder_band(x, y) && hu.at<short>(y, x) > 0) arc.at<uchar>(y, x) = 255;
  return arc;
}

TEST(HeadCtMask, CtBodyMaskExcludesHeadHolderArc) {
  VISPACK_REQUIRE_SAMPLE("head-ct");
  auto config = pipeline::load_config(sample_dir("head-ct") + "/config.json");
  auto hu = read_head_ct_hu();
  ASSERT_EQ(hu.size(), 108u);
  for (int z = 0; z < 106; ++z) {
    cv::Mat hu32;
    hu[z].convertTo(hu32, CV_32F);
    const double ct_mm2 = config.ct->pixel_spacing_mm[0] * config.ct->pixel_spacing_mm[1];
    cv::Mat mask =
        pipeline::ct_body_mask(hu32, config.mask.hu_threshold, config.mask.min_part_mm2 / ct_mm2);
    cv::Mat arc = arc_pixels(hu[z]);
    // The arc is there (>= 94 px per slice, HeadCt.HeadHolderArcIsWhereDocumented) ...
    ASSERT_GT(cv::countNonZero(arc), 80) << "slice " << z;
    EXPECT_EQ(cv::countNonZero(mask & arc), 0) << "slice " << z << ": mask covers the arc";
    // ... and the head stays: the brain centre (x 118..137, y 100..119) is body in mid slices.
    if (z >= 20 && z <= 80) {
      EXPECT_EQ(cv::countNonZero(mask(cv::Rect(118, 100, 20, 20))), 400) << "slice " << z;
    }
  }
}

TEST(VisibleWomanMask, GelRemovedByColourRefinement) {
  VISPACK_REQUIRE_SAMPLE("visible-woman");
  auto config = pipeline::load_config(sample_dir("visible-woman") + "/config.json");
  ASSERT_TRUE(config.mask.refine_gel);
  auto files = pipeline::list_slices(config.rgb);
  cv::Mat rgb = pipeline::read_slice(files.at(0).path);
  auto result = pipeline::compute_mask(rgb, nullptr, cv::Matx23d(1, 0, 0, 0, 1, 0), config.mask,
                                       config.spacing_mm[0] * config.spacing_mm[1]);
  ASSERT_EQ(result.mask.size(), rgb.size());
  const cv::Mat& m = result.mask;
  std::printf("visible-woman mask: coverage %.4f, gel (%.1f, %.1f, %.1f)\n", result.coverage,
              result.gel[0], result.gel[1], result.gel[2]);
  if (std::getenv("VISPACK_KEEP_TEST_DIRS"))
    pipeline::write_image("/tmp/visible-woman-mask.png", pipeline::draw_mask_overlay(rgb, m));
  const Box in = kVwInside;
  cv::Rect inside(in.x0, in.y0, in.x1 - in.x0 + 1, in.y1 - in.y0 + 1);
  EXPECT_EQ(cv::countNonZero(m(inside)), inside.area()) << "brain box not all body";
  for (const Box& b : kVwGel) {
    cv::Rect r(b.x0, b.y0, b.x1 - b.x0 + 1, b.y1 - b.y0 + 1);
    EXPECT_EQ(cv::countNonZero(m(r)), 0) << "gel box " << r << " is in the mask";
  }
  // The gel-filled nasal cavity is enclosed by tissue: it belongs to the body (mask.h step 4).
  cv::Rect cavity(62, 48, 11, 19);  // x 62..72, y 48..66 (docs/SAMPLES.md)
  EXPECT_EQ(cv::countNonZero(m(cavity)), cavity.area()) << "gel-filled cavity punched out";
  // Tissue (R > B + 10, R > 50) is 59.1 % of the slice; with the cavity and the dark skin edge
  // the mask measured 62.5 %. A mask that kept the gel or lost half the head is far outside.
  EXPECT_GT(result.coverage, 0.55);
  EXPECT_LT(result.coverage, 0.70);
  // The estimated gel colour is the dark blue of the border, about (20, 37, 58).
  EXPECT_NEAR(result.gel[0], 20.0, 8.0);
  EXPECT_NEAR(result.gel[1], 37.0, 8.0);
  EXPECT_NEAR(result.gel[2], 58.0, 8.0);
}

}  // namespace
}  // namespace vispack::test

// transforms.json round trip and the affine conventions of imaging/transforms.h (the types:
// core/transform_types.h) (docs/ARCHITECTURE.md "Slice transforms"): the rigid map of a colour
// slice and the inverse of ct_to_rgb.
#include <gtest/gtest.h>

#include <cmath>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/imaging/transforms.h"

using namespace vispack;
using namespace vispack::pipeline;

TEST(Transforms, JsonRoundTripAndConventions) {
  test::TempDir dir;
  StackTransforms t;
  t.width = 96;
  t.height = 64;
  t.center_px = {47.5, 31.5};
  SliceTransform s;
  s.index = 0;
  t.slices.push_back(s);
  s.index = 1;
  s.number = 1;
  s.rigid.dx_px = 1.5;
  s.rigid.dy_px = -2.25;
  s.rigid.rotation_deg = 10;
  s.jump = true;
  s.duplicate_of = 0;
  s.quality = 0.5;
  t.slices.push_back(s);
  t.ct_to_rgb = Similarity{2.0, 5.0, 1.0, -1.0};
  write_transforms(dir / "t.json", t);
  StackTransforms back = read_transforms(dir / "t.json");
  ASSERT_EQ(back.slices.size(), 2u);
  EXPECT_DOUBLE_EQ(back.slices[1].rigid.dx_px, 1.5);
  EXPECT_TRUE(back.slices[1].jump);
  EXPECT_EQ(back.slices[1].duplicate_of.value_or(-1), 0);
  EXPECT_DOUBLE_EQ(back.ct_to_rgb->scale, 2.0);

  // output_to_observed: the centre maps to c + d; +90 deg sends c + (1, 0) to c + d + (0, 1).
  SliceTransform r90;
  r90.rigid.rotation_deg = 90;
  r90.rigid.dx_px = 3;
  cv::Matx23d m = rigid_matrix(r90.rigid, {10, 20});
  EXPECT_NEAR(m(0, 0) * 11 + m(0, 1) * 20 + m(0, 2), 13.0, 1e-12);
  EXPECT_NEAR(m(1, 0) * 11 + m(1, 1) * 20 + m(1, 2), 21.0, 1e-12);
  // output_to_ct inverts q = c + s R (u - c_ct) + d.
  Similarity ct{2.0, 30.0, 4.0, -3.0};
  cv::Point2d c{47.5, 31.5}, cc{27.5, 27.5};
  double th = 30 * M_PI / 180, ux = 5, uy = 40;
  double qx = c.x + 2 * (std::cos(th) * (ux - cc.x) - std::sin(th) * (uy - cc.y)) + 4;
  double qy = c.y + 2 * (std::sin(th) * (ux - cc.x) + std::cos(th) * (uy - cc.y)) - 3;
  cv::Matx23d inv = output_to_ct(ct, c, cc);
  EXPECT_NEAR(inv(0, 0) * qx + inv(0, 1) * qy + inv(0, 2), ux, 1e-9);
  EXPECT_NEAR(inv(1, 0) * qx + inv(1, 1) * qy + inv(1, 2), uy, 1e-9);

  write_file_atomic(dir / "bad.json", R"({"width": 4, "height": 4, "slices": [{"dx_px": "a"}]})");
  EXPECT_THROW(read_transforms(dir / "bad.json"), FormatError);
}

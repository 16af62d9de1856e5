// vispack-vdb: vdb_print lists the three grids; reading back with OpenVDB gives the values of the
// intermediates, active only inside the mask, with the anisotropic voxel size.
#include <gtest/gtest.h>

#include <openvdb/openvdb.h>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/pipeline/phantom.h"
#include "vispack/pipeline/run.h"
#include "vispack/pipeline/slice_io.h"

using namespace vispack;
using namespace vispack::pipeline;

TEST(Vdb, GridsValuesAndVdbPrint) {
  test::TempDir dir;
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 6;
  po.quiet = true;
  make_phantom(dir.path(), po);
  Config config = load_config(dir / "config.json");
  RunOptions options;
  options.quiet = true;
  run_pipeline(config, options);

  // Expected values from the intermediates.
  std::uint64_t mask_voxels = 0;
  for (int k = 0; k < 24; ++k)
    mask_voxels += cv::countNonZero(read_slice(mask_path(config, k)));
  ASSERT_GT(mask_voxels, 1000u);

  std::string out;
  ASSERT_EQ(test::run_command("/usr/bin/vdb_print -l " + config.vdb_output, &out), 0) << out;
  for (const char* name : {"Name: ct", "Name: labels", "Name: rgb"})
    EXPECT_NE(out.find(name), std::string::npos) << out;
  EXPECT_NE(out.find("voxel dimensions: [0.5, 0.5, 1]"), std::string::npos) << out;

  openvdb::initialize();
  openvdb::io::File file(config.vdb_output);
  file.open();
  auto ct = openvdb::gridPtrCast<openvdb::FloatGrid>(file.readGrid("ct"));
  auto labels = openvdb::gridPtrCast<openvdb::Int32Grid>(file.readGrid("labels"));
  auto rgb = openvdb::gridPtrCast<openvdb::Vec3SGrid>(file.readGrid("rgb"));
  file.close();
  ASSERT_TRUE(ct && labels && rgb);
  EXPECT_EQ(ct->activeVoxelCount(), mask_voxels);
  EXPECT_EQ(labels->activeVoxelCount(), mask_voxels);
  EXPECT_EQ(rgb->activeVoxelCount(), mask_voxels);
  openvdb::Vec3d voxel = ct->voxelSize();
  EXPECT_DOUBLE_EQ(voxel[0], 0.5);
  EXPECT_DOUBLE_EQ(voxel[2], 1.0);
  // Every voxel of slices 0, 11 and 23 against the intermediates (exact: HU and IDs are integers,
  // colour is c / 255 in float).
  auto ct_acc = ct->getConstAccessor();
  auto lab_acc = labels->getConstAccessor();
  auto rgb_acc = rgb->getConstAccessor();
  for (int k : {0, 11, 23}) {
    cv::Mat m = read_slice(mask_path(config, k)), c = read_slice(mask_ct_path(config, k)),
            l = read_slice(labels_path(config, k)), r = read_slice(registered_rgb_path(config, k));
    for (int y = 0; y < m.rows; ++y)
      for (int x = 0; x < m.cols; ++x) {
        openvdb::Coord ijk(x, y, k);
        bool inside = m.at<std::uint8_t>(y, x) != 0;
        ASSERT_EQ(ct_acc.isValueOn(ijk), inside) << x << "," << y << "," << k;
        if (!inside) continue;
        ASSERT_EQ(ct_acc.getValue(ijk), float(int(c.at<std::uint16_t>(y, x)) - 32768));
        ASSERT_EQ(lab_acc.getValue(ijk), int(l.at<std::uint16_t>(y, x)));
        ASSERT_NEAR(rgb_acc.getValue(ijk)[1], r.at<cv::Vec3b>(y, x)[1] / 255.0f, 1e-6);
      }
  }
  // Command line: a shard is refused with a usage error.
  EXPECT_EQ(
      test::run_command(
          test::bin("vispack-vdb") + " --config " + dir / "config.json" + " --slices 0:5", &out),
      2)
      << out;
}

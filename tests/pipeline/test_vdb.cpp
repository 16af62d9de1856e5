// vispack-vdb: vdb_print lists the three grids; reading back with OpenVDB gives the values of the
// intermediates, active only inside the mask, with the anisotropic voxel size.
#include <gtest/gtest.h>

#include <openvdb/openvdb.h>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/run.h"
#include "vispack/pipeline/slice_io.h"
#include "vispack/pipeline/stage_run.h"
#include "vispack/pipeline/work_layout.h"

using namespace vispack;
using namespace vispack::pipeline;
using namespace vispack::phantom;

TEST(Vdb, GridsValuesAndVdbPrint) {
  test::TempDir dir;
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 6;
  po.quiet = true;
  make_phantom(dir.path(), po);
  {
    // The full-size registered colour and resampled CT are compared below as the register and
    // mask stages write them (work.write_registered / write_ct; off by default): the stages
    // rebuild them from the inputs, so this also checks that the copies agree.
    auto j = nlohmann::json::parse(read_file(dir / "config.json"));
    j["work"]["write_registered"] = true;
    j["work"]["write_ct"] = true;
    write_file_atomic(dir / "config.json", j.dump());
  }
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
  // Every voxel of every slice against the intermediates (exact: HU and IDs are integers, colour
  // is c / 255 in float, all three components), and inactive exactly outside the mask.
  auto ct_acc = ct->getConstAccessor();
  auto lab_acc = labels->getConstAccessor();
  auto rgb_acc = rgb->getConstAccessor();
  std::uint64_t checked = 0, wrong_active = 0, wrong_ct = 0, wrong_labels = 0, wrong_rgb = 0;
  for (int k = 0; k < 24; ++k) {
    cv::Mat m = read_slice(mask_path(config, k)), c = read_slice(mask_ct_path(config, k)),
            l = read_slice(labels_path(config, k)), r = read_slice(registered_rgb_path(config, k));
    for (int y = 0; y < m.rows; ++y)
      for (int x = 0; x < m.cols; ++x) {
        openvdb::Coord ijk(x, y, k);
        const bool inside = m.at<std::uint8_t>(y, x) != 0;
        if (ct_acc.isValueOn(ijk) != inside || lab_acc.isValueOn(ijk) != inside ||
            rgb_acc.isValueOn(ijk) != inside)
          ++wrong_active;
        if (!inside) continue;
        ++checked;
        if (ct_acc.getValue(ijk) != float(int(c.at<std::uint16_t>(y, x)) - 32768)) ++wrong_ct;
        if (lab_acc.getValue(ijk) != int(l.at<std::uint16_t>(y, x))) ++wrong_labels;
        const openvdb::Vec3s v = rgb_acc.getValue(ijk);
        for (int i = 0; i < 3; ++i)
          if (std::abs(v[i] - r.at<cv::Vec3b>(y, x)[i] / 255.0f) > 1e-6f) {
            ++wrong_rgb;
            break;
          }
      }
  }
  EXPECT_EQ(checked, mask_voxels);
  EXPECT_EQ(wrong_active, 0u);
  EXPECT_EQ(wrong_ct, 0u);
  EXPECT_EQ(wrong_labels, 0u);
  EXPECT_EQ(wrong_rgb, 0u);
  // Command line: a shard is refused with a usage error.
  EXPECT_EQ(
      test::run_command(
          test::bin("vispack-vdb") + " --config " + dir / "config.json" + " --slices 0:5", &out),
      2)
      << out;
}

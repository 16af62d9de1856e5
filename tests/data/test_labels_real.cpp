// Real-data accuracy of vispack-labels (docs/GOALS.md §6): the AAL atlas, colour-coded with 117
// labels and original IDs up to 9170, survives the labels stage with every voxel's ID exact — from
// the clean PNG slices, and from slices with deterministic colour noise inside the tolerance.
#include <gtest/gtest.h>

#include <filesystem>
#include <set>

#include <opencv2/core.hpp>

#include "samples.h"
#include "test_support.h"
#include "vispack/common/nrrd.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vispack::test {
namespace {

namespace fs = std::filesystem;

struct Comparison {
  std::size_t slices = 0, mismatches = 0;
  std::set<int> ids;
};

// Compares <work>/labels/labels_NNNN.png with truth/labels.nrrd, voxel by voxel.
Comparison compare_with_truth(const std::string& work_dir) {
  NrrdVolume truth = read_nrrd(sample_dir("aal") + "/truth/labels.nrrd");
  const auto nx = truth.dims[0], ny = truth.dims[1], nz = truth.dims[2];
  const std::uint16_t* want = truth.as<std::uint16_t>();
  Comparison c;
  for (std::int64_t z = 0; z < nz; ++z) {
    char name[32];
    std::snprintf(name, sizeof name, "/labels/labels_%04d.png", int(z));
    cv::Mat got = pipeline::read_slice(work_dir + name);
    EXPECT_EQ(got.type(), CV_16UC1) << name;
    EXPECT_EQ(got.cols, nx) << name;
    EXPECT_EQ(got.rows, ny) << name;
    if (got.type() != CV_16UC1 || got.cols != nx || got.rows != ny) return c;
    ++c.slices;
    for (int y = 0; y < ny; ++y) {
      const std::uint16_t* row = got.ptr<std::uint16_t>(y);
      for (int x = 0; x < nx; ++x) {
        c.ids.insert(row[x]);
        if (row[x] != want[(z * ny + y) * nx + x]) ++c.mismatches;
      }
    }
  }
  return c;
}

TEST(AalLabelsStage, EveryAtlasIdSurvivesExactly) {
  VISPACK_REQUIRE_SAMPLE("aal");
  TempDir dir("vispack-aal-labels");
  std::string config = write_sample_config("aal", dir.path());
  std::string out;
  int rc = run_command(bin("vispack-labels") + " --config " + config + " --quiet", &out);
  ASSERT_EQ(rc, 0) << out;
  Comparison c = compare_with_truth(dir.path() + "/work");
  EXPECT_EQ(c.slices, 181u);
  EXPECT_EQ(c.mismatches, 0u);
  EXPECT_EQ(c.ids.size(), 117u);  // background + 116 regions
  EXPECT_EQ(*c.ids.rbegin(), 9170);
}

// Colour noise of at most 10 per channel (distance <= 17.3 < tolerance 24; the palette's
// colours are at least 51 apart, so the nearest colour is always the right one): as a lossy
// encoder or anti-aliasing would leave. Every ID must still be exact.
TEST(AalLabelsStage, NoisyColoursWithinToleranceStillExact) {
  VISPACK_REQUIRE_SAMPLE("aal");
  TempDir dir("vispack-aal-labels-noisy");
  fs::create_directories(dir.path() + "/seg");
  pipeline::SliceSource seg{sample_dir("aal") + "/seg", "seg_{n}.png", std::nullopt};
  cv::RNG rng(20240611);  // fixed seed: the same noise every run
  for (const auto& file : pipeline::list_slices(seg)) {
    cv::Mat img = pipeline::read_slice(file.path), noise(img.size(), CV_16SC3), noisy;
    rng.fill(noise, cv::RNG::UNIFORM, -10, 11);
    img.convertTo(noisy, CV_16SC3);
    noisy += noise;
    noisy.convertTo(img, CV_8UC3);  // saturates at 0 and 255
    pipeline::write_image(dir.path() + "/seg/" + fs::path(file.path).filename().string(), img);
  }
  std::string config = write_sample_config(
      "aal", dir.path(), [&](nlohmann::json& j) { j["seg"]["dir"] = dir.path() + "/seg"; });
  std::string out;
  int rc = run_command(bin("vispack-labels") + " --config " + config + " --quiet", &out);
  ASSERT_EQ(rc, 0) << out;
  Comparison c = compare_with_truth(dir.path() + "/work");
  EXPECT_EQ(c.slices, 181u);
  EXPECT_EQ(c.mismatches, 0u);
  EXPECT_EQ(c.ids.size(), 117u);
}

}  // namespace
}  // namespace vispack::test

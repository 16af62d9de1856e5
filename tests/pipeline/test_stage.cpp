// StageRun: resume, staleness (config section, stage-wide input, slice input, outputs), shards,
// reports; the work folder's paths. transforms.json and the affine conventions:
// test_transforms.cpp.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <thread>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"

using namespace vispack;
using namespace vispack::pipeline;
namespace fs = std::filesystem;

namespace {

// A config over a folder of 6 empty "slices" (the loader only lists names).
Config make_config(const test::TempDir& dir, int hu = -400) {
  for (int i = 0; i < 6; ++i) {
    fs::create_directories(dir / "rgb");
    std::ofstream(dir / ("rgb/rgb_" + std::to_string(i) + ".png")) << "x";
  }
  nlohmann::json j = {
      {"spacing_mm", {1, 1, 1}}, {"rgb", {{"dir", "rgb"}}}, {"mask", {{"hu_threshold", hu}}}};
  write_file_atomic(dir / "c.json", j.dump());
  return load_config(dir / "c.json");
}

// A toy stage: output k = "<input k>-<hu>" in work/toy/out_k.txt; returns the slices computed.
int toy_stage(const Config& config, const StageOptions& options, const std::string& stage_input) {
  StageRun run(config, "toy", 6, options, {"mask"}, {stage_input});
  int computed = 0;
  for (int k = run.range().first; k < run.range().last; ++k) {
    std::string in = config.rgb.dir + "/rgb_" + std::to_string(k) + ".png";
    std::string fp = Fingerprint().file(in).str();
    std::string out = run.slice_path("out", k, "txt");
    if (run.up_to_date(k, fp, {out})) {
      run.skip(k);
      continue;
    }
    write_file_atomic(out, read_file(in) + "-" + std::to_string(config.mask.hu_threshold));
    run.done(k, fp, {out}, 1);
    ++computed;
  }
  run.set_quality("answer", 42);
  StageResult r = run.finish();
  EXPECT_EQ(r.processed, computed);
  return computed;
}

}  // namespace

TEST(Stage, ResumeAndStaleness) {
  test::TempDir dir;
  Config config = make_config(dir);
  StageOptions o;
  o.quiet = true;
  std::string side = dir / "side.json";
  write_file_atomic(side, "1");
  EXPECT_EQ(toy_stage(config, o, side), 6);
  EXPECT_EQ(toy_stage(config, o, side), 0);  // up to date
  auto report = nlohmann::json::parse(read_file(dir / "work/toy/report.json"));
  EXPECT_EQ(report["quality"]["answer"], 42);  // kept from the computing run
  EXPECT_EQ(report["processed"], 6);

  // One input changed: only that slice.
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  std::ofstream(dir / "rgb/rgb_3.png") << "changed";
  EXPECT_EQ(toy_stage(config, o, side), 1);
  // One output deleted or overwritten: only that slice.
  fs::remove(dir / "work/toy/out_0001.txt");
  EXPECT_EQ(toy_stage(config, o, side), 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  std::ofstream(dir / "work/toy/out_0002.txt") << "tampered";
  EXPECT_EQ(toy_stage(config, o, side), 1);
  // Stage-wide input changed: everything.
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  write_file_atomic(side, "2");
  EXPECT_EQ(toy_stage(config, o, side), 6);
  // Config section changed: everything; an unrelated section: nothing.
  Config other = make_config(dir, -300);
  EXPECT_EQ(toy_stage(other, o, side), 6);
  EXPECT_EQ(read_file(dir / "work/toy/out_0000.txt"), "x--300.000000");
  EXPECT_EQ(toy_stage(other, o, side), 0);
  // --force: everything.
  StageOptions force = o;
  force.force = true;
  EXPECT_EQ(toy_stage(other, force, side), 6);
}

TEST(Stage, ShardsCombine) {
  test::TempDir dir;
  Config config = make_config(dir);
  std::string side = dir / "side.json";
  write_file_atomic(side, "1");
  StageOptions a, b;
  a.quiet = b.quiet = true;
  a.slices = "0:2";
  b.slices = "2:";
  EXPECT_EQ(toy_stage(config, a, side), 2);
  EXPECT_TRUE(fs::exists(dir / "work/toy/manifest-0-2.json"));
  EXPECT_TRUE(fs::exists(dir / "work/toy/report-0-2.json"));
  EXPECT_EQ(toy_stage(config, b, side), 4);
  // An unsharded run sees both shards' records, computes nothing and folds the manifests.
  StageOptions all;
  all.quiet = true;
  EXPECT_EQ(toy_stage(config, all, side), 0);
  EXPECT_TRUE(fs::exists(dir / "work/toy/manifest.json"));
  EXPECT_FALSE(fs::exists(dir / "work/toy/manifest-0-2.json"));
  StageOptions bad;
  bad.quiet = true;
  bad.slices = "4:2";
  EXPECT_THROW(toy_stage(config, bad, side), UsageError);
}

TEST(Stage, WorkFolderPaths) {
  test::TempDir dir;
  Config config = make_config(dir);
  EXPECT_EQ(mask_path(config, 7), dir / "work/mask/mask_0007.png");
  EXPECT_EQ(labels_path(config, 12345), dir / "work/labels/labels_12345.png");
  EXPECT_EQ(registered_rgb_path(config, 0), dir / "work/register/registered/rgb_0000.png");
  EXPECT_EQ(stack_slices(config).size(), 6u);
}

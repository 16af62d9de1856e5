// vispack-run on the tiny phantom: a full run, a second run that skips everything, and a touched
// mask section that reruns mask and the later stages only.
#include <gtest/gtest.h>

#include <map>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/run/run.h"

using namespace vispack;
using namespace vispack::pipeline;
using namespace vispack::phantom;

namespace {
std::map<std::string, StageResult> by_stage(const std::vector<StageResult>& results) {
  std::map<std::string, StageResult> out;
  for (const auto& r : results)
    out[r.stage] = r;
  return out;
}
}  // namespace

TEST(Run, FullRunThenSkipThenPartialRerun) {
  test::TempDir dir;
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 5;
  po.quiet = true;
  make_phantom(dir.path(), po);
  Config config = load_config(dir / "config.json");
  RunOptions options;
  options.quiet = true;

  auto first = by_stage(run_pipeline(config, options));
  ASSERT_EQ(first.size(), 5u);
  for (const char* s : {"register", "mask", "labels"})
    EXPECT_EQ(first[s].processed, 24) << s;
  EXPECT_EQ(first["pack"].processed, 1);
  EXPECT_EQ(first["vdb"].processed, 1);
  EXPECT_EQ(first["pack"].output, config.output);

  // A second run with nothing changed recomputes nothing (it checks only stats files and
  // manifests; how long that takes is the start-up benchmark's business, not this test's).
  auto second = by_stage(run_pipeline(config, options));
  for (auto& [name, r] : second)
    EXPECT_EQ(r.processed, 0) << name << " reran with nothing changed";

  // Touch a key only the mask stage reads: mask and everything after it rerun, register does not.
  // (Register must list only the mask keys it reads, e.g. "mask.hu_threshold", in its StageRun.)
  auto j = nlohmann::json::parse(read_file(dir / "config.json"));
  j["mask"]["opening_px"] = 2;
  write_file_atomic(dir / "config.json", j.dump(2));
  Config touched = load_config(dir / "config.json");
  auto third = by_stage(run_pipeline(touched, options));
  EXPECT_EQ(third["register"].processed, 0);
  EXPECT_EQ(third["mask"].processed, 24);
  EXPECT_EQ(third["pack"].processed, 1);
  EXPECT_EQ(third["vdb"].processed, 1);
  // labels reads no mask output: it stays up to date.
  EXPECT_EQ(third["labels"].processed, 0);

  // --from/--to select stages; --force recomputes them.
  RunOptions only_pack = options;
  only_pack.from = only_pack.to = "pack";
  only_pack.force = true;
  auto forced = run_pipeline(touched, only_pack);
  ASSERT_EQ(forced.size(), 1u);
  EXPECT_EQ(forced[0].stage, "pack");
  EXPECT_EQ(forced[0].processed, 1);
  RunOptions bad = options;
  bad.from = "vdb";
  bad.to = "mask";
  EXPECT_THROW(run_pipeline(touched, bad), UsageError);
  bad.from = "colour";
  EXPECT_THROW(run_pipeline(touched, bad), UsageError);
}

TEST(Run, CommandLine) {
  std::string out;
  EXPECT_EQ(test::run_command(test::bin("vispack-run") + " --help", &out), 0);
  EXPECT_NE(out.find("--from"), std::string::npos);
  EXPECT_EQ(test::run_command(test::bin("vispack-run") + " /nonexistent/config.json", &out), 3)
      << out;
  test::TempDir dir;
  write_file_atomic(dir / "c.json", R"({"spacing_mm": [1, 1, 1], "rgb": {"dir": "nowhere"}})");
  EXPECT_EQ(test::run_command(test::bin("vispack-run") + " " + dir / "c.json", &out), 5) << out;
  EXPECT_NE(out.find("rgb.dir"), std::string::npos) << out;
}

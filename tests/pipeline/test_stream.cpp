// The streaming vispack-run (stream.h) against the staged one: the same packed file byte for byte
// and the same mask, overlay and label PNGs (plain, cropped, keeping what lies outside the body);
// each finds the other's work up to date; a stream stopped by an error resumes without
// recomputing the slices it finished; a changed slice or config section reruns what depends on it.
#include <gtest/gtest.h>

#include <filesystem>
#include <map>

#include "packed_compare.h"
#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/pack/pack.h"
#include "vispack/pipeline/register/register_stage.h"
#include "vispack/pipeline/run/run.h"
#include "vispack/pipeline/run/stream.h"

using namespace vispack;
using namespace vispack::pipeline;
namespace fs = std::filesystem;

namespace {

constexpr int kSlices = 24;  // the tiny preset

// The tiny phantom (CT, colour segmentation with a palette, a black and a duplicated slice) in
// `dir`, its config patched with `patch` (JSON merge patch) and 8-slice bricks (three slabs); with
// `every` > 1 a CT and a segmentation slice only at every `every`-th colour slice
// (docs/ARCHITECTURE.md, 'Each input at its own z': the CT interpolated along z, the labels from
// the nearest segmentation slice).
Config make_case(const test::TempDir& dir, const nlohmann::json& patch, int every = 1) {
  phantom::PhantomOptions po;
  po.preset = "tiny";
  po.seed = 7;
  po.defects = true;
  po.quiet = true;
  po.ct_every = every;
  po.seg_every = every;
  phantom::make_phantom(dir.path(), po);
  auto j = nlohmann::json::parse(read_file(dir / "config.json"));
  j["pack"]["brick_edge"] = 8;
  j.merge_patch(patch);
  write_file_atomic(dir / "config.json", j.dump(2));
  return load_config(dir / "config.json");
}

std::map<std::string, StageResult> run(const Config& config, bool staged, int threads,
                                       bool force = false) {
  RunOptions options;
  options.quiet = true;
  options.staged = staged;
  options.threads = threads;
  options.force = force;
  options.to = "pack";
  std::map<std::string, StageResult> out;
  for (const auto& r : run_pipeline(config, options))
    out[r.stage] = r;
  return out;
}

// The packed file and every mask, overlay and label PNG of `b` equal those of `a`, byte for byte.
void expect_same_products(const Config& a, const Config& b) {
  ASSERT_TRUE(fs::exists(a.output));
  ASSERT_TRUE(fs::exists(b.output));
  EXPECT_TRUE(read_file(a.output) == read_file(b.output)) << "packed files differ";
  for (int k = 0; k < kSlices; ++k) {
    for (const auto& [x, y] : {std::pair{mask_path(a, k), mask_path(b, k)},
                               std::pair{slice_output_path(a, "mask", "overlay", k),
                                         slice_output_path(b, "mask", "overlay", k)},
                               std::pair{labels_path(a, k), labels_path(b, k)}}) {
      ASSERT_TRUE(fs::exists(x)) << x;
      ASSERT_TRUE(fs::exists(y)) << y;
      EXPECT_TRUE(read_file(x) == read_file(y)) << x << " differs from " << y;
    }
  }
}

void expect_up_to_date(const std::map<std::string, StageResult>& results) {
  ASSERT_EQ(results.size(), 4u);
  for (const auto& [name, r] : results)
    EXPECT_EQ(r.processed, 0) << name << " recomputed although nothing changed";
}

// Staged in one folder (one thread), streaming in another (three threads: slices finish out of
// order); same products; then each kind of run finds the other's work up to date.
void check_stream_equals_staged(const nlohmann::json& patch, int every = 1) {
  test::TempDir staged_dir, stream_dir;
  const Config staged = make_case(staged_dir, patch, every);
  const Config stream = make_case(stream_dir, patch, every);
  auto s = run(staged, true, 1);
  auto t = run(stream, false, 3);
  for (const char* stage : {"mask", "labels"}) {
    EXPECT_EQ(s[stage].processed, kSlices) << stage;
    EXPECT_EQ(t[stage].processed, kSlices) << stage;
  }
  EXPECT_EQ(t["pack"].processed, 1);
  expect_same_products(staged, stream);
  expect_up_to_date(run(staged, false, 2));
  expect_up_to_date(run(stream, true, 2));
}

}  // namespace

TEST(Stream, SameFilesAsTheStagedRun) {
  check_stream_equals_staged(nlohmann::json::object());
}

TEST(Stream, SameFilesAsTheStagedRunWithCrop) {
  // The crop box is the union of every mask: the stream writes masks first, then packs.
  check_stream_equals_staged({{"pack", {{"crop_margin_px", 3}}}});
}

TEST(Stream, SameFilesAsTheStagedRunKeepingOutsideBody) {
  check_stream_equals_staged({{"pack", {{"keep_outside_body", "all"}}}});
}

TEST(Stream, ResumesAfterAnErrorWithoutRecomputingFinishedSlices) {
  test::TempDir ref_dir, dir;
  const Config ref = make_case(ref_dir, nlohmann::json::object());
  const Config config = make_case(dir, nlohmann::json::object());
  run(ref, true, 1);
  StageOptions options;
  options.quiet = true;
  options.threads = 1;  // slices in stack order: 0..11 finish, slice 12 fails
  run_register_stage(config, options);
  const std::string victim = stack_slices(config)[12].path;
  const std::string bytes = read_file(victim);
  const auto mtime = fs::last_write_time(victim);
  write_file_atomic(victim, "not a PNG");
  try {
    run_stream(config, options);
    ADD_FAILURE() << "a corrupt slice must stop the stream";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find(victim), std::string::npos) << e.what();
  }
  EXPECT_FALSE(fs::exists(config.output)) << "a half-written packed file was left";
  // The slice back as it was (same bytes, same mtime: register stays up to date).
  write_file_atomic(victim, bytes);
  fs::last_write_time(victim, mtime);
  std::map<std::string, StageResult> resumed;
  for (const auto& r : run_stream(config, options))
    resumed[r.stage] = r;
  EXPECT_EQ(resumed["mask"].processed, kSlices - 12);
  EXPECT_EQ(resumed["mask"].skipped, 12);
  EXPECT_EQ(resumed["labels"].processed, kSlices - 12);
  EXPECT_EQ(resumed["labels"].skipped, 12);
  EXPECT_EQ(resumed["pack"].processed, 1);
  expect_same_products(ref, config);
  expect_up_to_date(run(config, true, 1));
}

TEST(Stream, ChangedInputOrSectionRerunsWhatDependsOnIt) {
  test::TempDir dir;
  const Config config = make_case(dir, nlohmann::json::object());
  run(config, false, 2);
  // A seg slice rewritten (same content, new mtime): its labels and the pack rerun, no mask.
  std::vector<SliceFile> seg = list_slices(*config.seg);
  const std::string content = read_file(seg[5].path);
  fs::last_write_time(seg[5].path, fs::last_write_time(seg[5].path) + std::chrono::seconds(5));
  ASSERT_EQ(read_file(seg[5].path), content);
  auto r = run(config, false, 2);
  EXPECT_EQ(r["register"].processed, 0);
  EXPECT_EQ(r["mask"].processed, 0);
  EXPECT_EQ(r["labels"].processed, 1);
  EXPECT_EQ(r["pack"].processed, 1);
  // A mask key: every mask and the pack rerun, labels stay.
  auto j = nlohmann::json::parse(read_file(dir / "config.json"));
  j["mask"]["opening_px"] = 2;
  write_file_atomic(dir / "config.json", j.dump(2));
  const Config touched = load_config(dir / "config.json");
  r = run(touched, false, 2);
  EXPECT_EQ(r["register"].processed, 0);
  EXPECT_EQ(r["mask"].processed, kSlices);
  EXPECT_EQ(r["labels"].processed, 0);
  EXPECT_EQ(r["pack"].processed, 1);
  expect_up_to_date(run(touched, true, 1));
  // --force recomputes every slice of the stream.
  r = run(touched, false, 2, true);
  EXPECT_EQ(r["mask"].processed, kSlices);
  EXPECT_EQ(r["labels"].processed, kSlices);
  EXPECT_EQ(r["pack"].processed, 1);
}

// vispack-run --slices A:B (a cluster's per-slice job): register, then the streaming pass over
// the shard, whose pack writes the slab files of the slabs that start in it. Shards [12, 24) and
// [0, 12) of 24 slices in 8-slice slabs: the first streams slab 2 (it ends inside the range); the
// second's slab 1 ([8, 16)) ends outside it, so that shard streams masks and labels and then packs
// slabs 0 and 1 from the work folder (slices 12..15 are there: the other shard ran first). The
// merge gives the whole-stack staged file byte for byte, and every mask and label PNG equals the
// staged run's; a second pass over each shard recomputes nothing. As on a cluster
// (scripts/vispack-slurm has no solve job), the shards' register runs solve the stack
// themselves: the measure shards leave no transforms.json, the first shard writes the staged
// run's bytes and the second finds them; rewritten with the same bytes (a third shard solving at
// the same time: a new mtime), it leaves every slab and stage up to date, as the merge and the
// second pass show.
namespace {

void check_shards_then_merge(int every) {
  test::TempDir staged_dir, dir;
  const Config staged = make_case(staged_dir, nlohmann::json::object(), every);
  const Config config = make_case(dir, nlohmann::json::object(), every);
  run(staged, true, 1);
  const std::vector<SliceFile> stack = stack_slices(config);
  EXPECT_TRUE(PackStream::streamable(config, stack, {12, 24}));
  EXPECT_FALSE(PackStream::streamable(config, stack, {0, 12}));
  EXPECT_FALSE(PackStream::streamable(config, stack, {9, 15}));  // starts no slab
  EXPECT_TRUE(PackStream::streamable(config, stack, {0, kSlices}));
  // The cluster's register-measure shards (vispack-slurm) first.
  StageOptions quiet;
  quiet.quiet = true;
  quiet.records_only = true;  // as vispack-slurm runs them with two shards or more
  for (const char* range : {"0:12", "12:24"}) {
    quiet.slices = range;
    run_register_stage(config, quiet);
  }
  quiet.slices.clear();
  quiet.records_only = false;
  // The measure shards stop at their records (register_stage.h): none solved.
  const std::string transforms = transforms_path(config);
  ASSERT_FALSE(fs::exists(transforms)) << "a measure shard solved the stack";
  // The staged run's solve of the same stack.
  const std::string solved = read_file(transforms_path(staged));
  std::map<std::string, std::map<std::string, StageResult>> shard;
  for (const char* range : {"12:24", "0:12"}) {
    RunOptions options;
    options.quiet = true;
    options.threads = 3;  // slices finish out of order
    options.slices = range;
    for (const auto& r : run_pipeline(config, options))
      shard[range][r.stage] = r;
  }
  EXPECT_EQ(shard["12:24"]["mask"].processed, 12);
  EXPECT_EQ(shard["12:24"]["labels"].processed, 12);
  EXPECT_EQ(shard["12:24"]["pack-slabs"].processed, 1);  // slab 2
  EXPECT_EQ(shard["0:12"]["pack-slabs"].processed, 2);   // slabs 0 and 1
  EXPECT_EQ(shard["0:12"].count("vdb"), 0u) << "a shard stops at pack";
  EXPECT_FALSE(fs::exists(config.output)) << "a shard wrote the packed file";
  ASSERT_TRUE(fs::exists(transforms)) << "no shard solved the stack";
  EXPECT_TRUE(read_file(transforms) == solved) << "the shards' solve differs from the measure's";
  const auto written = fs::last_write_time(transforms);
  write_file_atomic(transforms, solved);  // the same bytes, a new file
  ASSERT_NE(fs::last_write_time(transforms), written);
  run_pack_merge(config, quiet);
  expect_same_products(staged, config);
  for (const char* range : {"12:24", "0:12"}) {
    RunOptions options;
    options.quiet = true;
    options.slices = range;
    for (const auto& r : run_pipeline(config, options))
      EXPECT_EQ(r.processed, 0) << range << ": " << r.stage << " recomputed";
  }
}

}  // namespace

TEST(Stream, ShardsThenMergeGiveTheWholeStackFile) {
  check_shards_then_merge(1);
}

// A CT and a segmentation slice at every 3rd colour slice; the shards' interpolated CT,
// masks, nearest-in-z labels and slabs give the whole-stack run's products byte for byte.
TEST(Stream, ShardsThenMergeWithCtAndSegAtEveryThirdSlice) {
  check_shards_then_merge(3);
}

TEST(Stream, SameFilesAsTheStagedRunWithCtAndSegAtEveryThirdSlice) {
  check_stream_equals_staged(nlohmann::json::object(), 3);
}

TEST(Stream, ShardRangeHoldingPackAndVdbIsRefused) {
  test::TempDir dir;
  const Config config = make_case(dir, {{"vdb", {{"enabled", true}}}});
  RunOptions options;
  options.quiet = true;
  options.slices = "0:8";
  options.to = "vdb";
  EXPECT_THROW(run_pipeline(config, options), UsageError);
}

// Colour files 7, 15, 16 and 17 missing (numbers; CT and segmentation at every 3rd slot): the
// streaming shards place each file at its slot and the empty slots between, so shards named by
// stack indices tile the volume and their merge is the whole-stack run's file byte for byte,
// with the complete stack's depth and each slice at the complete stack's z
// (docs/ARCHITECTURE.md "Each input at its own z").
TEST(Stream, ShardsOfAStackWithMissingColourFilesTileTheVolume) {
  test::TempDir whole_dir, dir, staged_dir;
  const Config whole = make_case(whole_dir, nlohmann::json::object(), 3);
  const Config config = make_case(dir, nlohmann::json::object(), 3);
  const Config staged = make_case(staged_dir, nlohmann::json::object(), 3);
  const std::vector<int> gone = {7, 15, 16, 17};
  for (const Config* c : {&config, &staged})
    for (int k : gone) {
      char name[32];
      std::snprintf(name, sizeof name, "/rgb_%04d.png", k);
      ASSERT_TRUE(fs::remove(c->rgb.dir + name)) << c->rgb.dir + name;
    }
  run(whole, false, 2);
  run(staged, true, 1);
  // Stack slices 0..6 lie at z 0..6, 7..12 at 8..13, 13..19 at 18..23: 0:7 covers z [0, 8)
  // (slab 0), 7:20 z [8, 24) (slabs 1 and 2); 0:8 covers z [0, 9) and slab 1 ends at 16.
  const std::vector<SliceFile> stack = stack_slices(config);
  ASSERT_EQ(stack.size(), 20u);
  EXPECT_TRUE(PackStream::streamable(config, stack, {0, 7}));
  EXPECT_TRUE(PackStream::streamable(config, stack, {7, 20}));
  EXPECT_FALSE(PackStream::streamable(config, stack, {0, 8}));
  StageOptions quiet;
  quiet.quiet = true;
  run_register_stage(config, quiet);  // the shards find the stack solved
  std::map<std::string, std::map<std::string, StageResult>> shard;
  for (const char* range : {"7:20", "0:7"}) {
    RunOptions options;
    options.quiet = true;
    options.threads = 3;
    options.slices = range;
    for (const auto& r : run_pipeline(config, options))
      shard[range][r.stage] = r;
  }
  EXPECT_EQ(shard["7:20"]["mask"].processed, 13);
  EXPECT_EQ(shard["7:20"]["pack-slabs"].processed, 2);  // slabs 1 and 2, streamed
  EXPECT_EQ(shard["0:7"]["pack-slabs"].processed, 1);   // slab 0, slot 7 empty
  run_pack_merge(config, quiet);
  ASSERT_TRUE(fs::exists(config.output));
  EXPECT_TRUE(read_file(config.output) == read_file(staged.output))
      << "the streamed shards' merge differs from the staged whole-stack run";
  const test::PackedLevel0 gap_volume = test::read_packed_level0(config.output);
  EXPECT_EQ(gap_volume.dims[2], kSlices);
  // Labels to 85 %: the segmentation slice at z 15 was drawn on the missing file's grid and is
  // carried by its nearest file's (z 14) transform (slice_z.h colour_slice_of_seg); 89 % measured.
  test::expect_gaps_at_their_z(gap_volume, test::read_packed_level0(whole.output), gone, 0.97, 0.97,
                               0.85);
}

// Sharded vispack-pack (--slices shards writing slab files, then --merge): the merged file is
// byte-identical to a whole-stack pack, whatever the split; resume keeps finished slabs; a
// missing, out-of-date or corrupt slab file stops the merge with an error naming it.
#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/pack/pack.h"
#include "vispack/pipeline/run/run.h"

using namespace vispack;
using namespace vispack::pipeline;
namespace fs = std::filesystem;

namespace {

// Runs the pipeline up to pack (one process, whole stack) on `config`; returns the packed bytes.
std::string pack_whole(const Config& config) {
  RunOptions options;
  options.quiet = true;
  options.to = "pack";
  run_pipeline(config, options);
  return read_file(config.output);
}

// One tiny phantom (96x64x24) run to the labels stage, with brick_edge 8 (3 level-0 slabs, 4
// levels), and the whole-stack pack of it: shared by every test (each works on its own copy of
// the work folder's pack outputs).
class PackShards : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = std::make_unique<test::TempDir>("vispack-pack-shards");
    phantom::PhantomOptions po;
    po.preset = "tiny";
    po.seed = 11;
    po.quiet = true;
    phantom::make_phantom(dir_->path(), po);
    const std::string path = *dir_ / "config.json";
    nlohmann::json raw = nlohmann::json::parse(read_file(path));
    raw["pack"]["brick_edge"] = 8;
    raw["vdb"]["enabled"] = false;
    write_file_atomic(path, raw.dump(2));
    whole_ = new std::string(pack_whole(load_config(path)));
  }
  static void TearDownTestSuite() {
    delete whole_;
    whole_ = nullptr;
    dir_.reset();
  }

  void SetUp() override {
    config_ = load_config(*dir_ / "config.json");
    // Each test starts with no output and no slab files (and no pack records).
    fs::remove(config_.output);
    fs::remove_all(config_.work_dir + "/pack-slabs");
    fs::remove_all(config_.work_dir + "/pack");
  }

  StageOptions shard(const std::string& slices) const {
    StageOptions o;
    o.slices = slices;
    o.quiet = true;
    return o;
  }
  StageOptions quiet() const { return shard(""); }
  std::string slab(int bz) const {
    char name[32];
    std::snprintf(name, sizeof name, "slab_%04d.vpkslab", bz);
    return config_.work_dir + "/pack-slabs/" + name;
  }
  // Runs the shards, then the merge; returns the merged file's bytes.
  std::string shards_then_merge(const std::vector<std::string>& shards) {
    for (const auto& s : shards)
      run_pack_stage(config_, shard(s));
    run_pack_merge(config_, quiet());
    return read_file(config_.output);
  }

  static std::unique_ptr<test::TempDir> dir_;
  static std::string* whole_;
  Config config_;
};
std::unique_ptr<test::TempDir> PackShards::dir_;
std::string* PackShards::whole_ = nullptr;

// The message of the error `fn` throws, or "" (and a test failure) if it throws none.
template <class E, class F>
std::string error_of(F fn) {
  try {
    fn();
  } catch (const E& e) {
    return e.what();
  }
  ADD_FAILURE() << "no error thrown";
  return "";
}

}  // namespace

TEST_F(PackShards, OneShardHoldingEverySlab) {
  // 0:23 is a partial range (a shard) whose slab starts 0, 8, 16 all lie inside it.
  std::string merged = shards_then_merge({"0:23"});
  for (int bz = 0; bz < 3; ++bz)
    EXPECT_TRUE(fs::exists(slab(bz))) << slab(bz);
  ASSERT_EQ(merged.size(), whole_->size());
  EXPECT_TRUE(merged == *whole_) << "merged file differs from the whole-stack pack";
}

TEST_F(PackShards, TwoShardsByteIdentical) {
  std::string merged = shards_then_merge({"12:24", "0:12"});  // any order
  ASSERT_EQ(merged.size(), whole_->size());
  EXPECT_TRUE(merged == *whole_) << "merged file differs from the whole-stack pack";
}

TEST_F(PackShards, ThreeUnevenShardsByteIdentical) {
  // Slab starts: 0 in [0, 5), 8 in [5, 13), 16 in [13, 24).
  std::string merged = shards_then_merge({"0:5", "5:13", "13:24"});
  ASSERT_EQ(merged.size(), whole_->size());
  EXPECT_TRUE(merged == *whole_) << "merged file differs from the whole-stack pack";
  // A vispack-run after the merge finds pack up to date (same input fingerprint).
  StageResult again = run_pack_stage(config_, quiet());
  EXPECT_EQ(again.processed, 0);
}

TEST_F(PackShards, ShardWithoutSlabStartDoesNothing) {
  StageResult r = run_pack_stage(config_, shard("1:8"));  // no slab starts in [1, 8)
  EXPECT_EQ(r.processed, 0);
  EXPECT_FALSE(fs::exists(slab(0)));
  EXPECT_FALSE(fs::exists(slab(1)));
}

TEST_F(PackShards, MissingShardNamed) {
  run_pack_stage(config_, shard("0:12"));
  std::string message = error_of<InputError>([&] { run_pack_merge(config_, quiet()); });
  EXPECT_NE(message.find("slab_0002.vpkslab"), std::string::npos) << message;
  EXPECT_NE(message.find("--slices 16:24"), std::string::npos) << message;
  EXPECT_FALSE(fs::exists(config_.output));

  // The executable: one line, exit code 6 (InputError), naming the slab file.
  test::CommandResult r = test::run_command_split(test::bin("vispack-pack") + " --config " +
                                                  *dir_ / "config.json" + " --merge --quiet");
  EXPECT_EQ(r.code, 6) << r.err;
  EXPECT_EQ(r.err.rfind("vispack-pack: error: ", 0), 0u) << r.err;
  EXPECT_NE(r.err.find("slab_0002.vpkslab: missing"), std::string::npos) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
}

TEST_F(PackShards, ResumeKeepsFinishedSlabs) {
  StageResult first = run_pack_stage(config_, shard("0:12"));
  EXPECT_EQ(first.processed, 2);
  const auto t0 = fs::last_write_time(slab(0)), t1 = fs::last_write_time(slab(1));
  // The failed (here: never run) shard is resubmitted alone; the finished one is not redone.
  StageResult again = run_pack_stage(config_, shard("0:12"));
  EXPECT_EQ(again.processed, 0);
  EXPECT_EQ(again.skipped, 2);
  EXPECT_EQ(fs::last_write_time(slab(0)), t0);
  EXPECT_EQ(fs::last_write_time(slab(1)), t1);
  StageResult rest = run_pack_stage(config_, shard("12:24"));
  EXPECT_EQ(rest.processed, 1);
  run_pack_merge(config_, quiet());
  EXPECT_TRUE(read_file(config_.output) == *whole_);
  // --force redoes a shard's slabs.
  StageOptions force = shard("0:12");
  force.force = true;
  EXPECT_EQ(run_pack_stage(config_, force).processed, 2);
}

TEST_F(PackShards, CorruptSlabRefused) {
  shards_then_merge({"0:12", "12:24"});
  fs::remove(config_.output);
  fs::remove_all(config_.work_dir + "/pack");
  // Flip one byte in the middle of slab 1 (a payload or record): the slab's checksum catches it.
  std::string bytes = read_file(slab(1));
  bytes[bytes.size() / 2] = char(bytes[bytes.size() / 2] ^ 0x5A);
  {
    std::ofstream out(slab(1), std::ios::binary | std::ios::trunc);
    out.write(bytes.data(), std::streamsize(bytes.size()));
  }
  std::string message = error_of<FormatError>([&] { run_pack_merge(config_, quiet()); });
  EXPECT_NE(message.find("slab_0001.vpkslab"), std::string::npos) << message;
  EXPECT_FALSE(fs::exists(config_.output));
}

TEST_F(PackShards, OutOfDateSlabRefused) {
  run_pack_stage(config_, shard("0:12"));
  run_pack_stage(config_, shard("12:24"));
  // An intermediate of slice 9 (slab 1) is rewritten after its slab was encoded.
  const std::string mask = config_.work_dir + "/mask/mask_0009.png";
  std::string png = read_file(mask);
  fs::remove(mask);
  write_file_atomic(mask, png);
  std::string message = error_of<InputError>([&] { run_pack_merge(config_, quiet()); });
  EXPECT_NE(message.find("slab_0001.vpkslab: out of date"), std::string::npos) << message;
  EXPECT_NE(message.find("--slices 8:16"), std::string::npos) << message;
  // Rerunning the shard redoes that slab only; the merge then matches again.
  EXPECT_EQ(run_pack_stage(config_, shard("0:12")).processed, 1);
  run_pack_merge(config_, quiet());
  EXPECT_TRUE(read_file(config_.output) == *whole_);
}

// With the volume cropped to the bodies (pack.crop_margin_px, docs/ARCHITECTURE.md, 'The packed
// file') and the colour outside the body kept: the shards pack the same box and the merge equals
// the whole-stack pack of it; a slab written before the crop changed is refused as out of date, not
// merged.
TEST_F(PackShards, CroppedAndKeptByteIdentical) {
  const std::string path = *dir_ / "config.json";
  const std::string original = read_file(path);
  nlohmann::json raw = nlohmann::json::parse(original);
  raw["pack"]["crop_margin_px"] = 3;
  raw["pack"]["keep_outside_body"] = "colour";
  write_file_atomic(path, raw.dump(2));
  config_ = load_config(path);
  run_pack_stage(config_, quiet());
  const std::string whole = read_file(config_.output);
  EXPECT_NE(whole, *whole_) << "the crop changed nothing";
  fs::remove(config_.output);
  fs::remove_all(config_.work_dir + "/pack");
  const std::string merged = shards_then_merge({"0:9", "9:24"});
  EXPECT_TRUE(merged == whole) << "merged file differs from the whole-stack pack of the crop";
  // Back to the uncropped config: the cropped slabs are out of date for the merge.
  write_file_atomic(path, original);
  config_ = load_config(path);
  fs::remove(config_.output);
  fs::remove_all(config_.work_dir + "/pack");
  const std::string message = error_of<InputError>([&] { run_pack_merge(config_, quiet()); });
  EXPECT_NE(message.find("slab_0000.vpkslab"), std::string::npos) << message;
  // And the other way: slabs of the uncropped config, merged under the crop. The merge takes the
  // body bounds from the first slab's header (it reads no mask), and these slabs have none.
  shards_then_merge({"0:9", "9:24"});
  write_file_atomic(path, raw.dump(2));
  config_ = load_config(path);
  fs::remove(config_.output);
  const std::string refused = error_of<InputError>([&] { run_pack_merge(config_, quiet()); });
  EXPECT_NE(refused.find("slab_0000.vpkslab: written without pack.crop_margin_px"),
            std::string::npos)
      << refused;
  EXPECT_NE(refused.find("--slices 0:8"), std::string::npos) << refused;
  write_file_atomic(path, original);
  config_ = load_config(path);
}

// An odd slice count (21: the last slab short and odd, so its last level-1 slice comes from one
// slice), at brick edges 8 (3 slabs), 32 (one short slab) and 128 (the volume fits one brick: a
// single level, whose slab the merge's Writer copies from its file only at finish()): the merge,
// fed the shards' level-1 slices, equals the whole-stack pack byte for byte.
TEST(PackShardsShapes, OddSliceCountShortLastSlabEdges8And32AndOneBrick) {
  test::TempDir dir("vispack-pack-shards-odd");
  phantom::PhantomOptions po;
  po.preset = "tiny";
  po.seed = 12;
  po.slices = 21;
  po.quiet = true;
  phantom::make_phantom(dir.path(), po);
  const std::string path = dir / "config.json";
  nlohmann::json raw = nlohmann::json::parse(read_file(path));
  raw["vdb"]["enabled"] = false;
  for (int edge : {8, 32, 128}) {
    raw["pack"]["brick_edge"] = edge;
    write_file_atomic(path, raw.dump(2));
    Config config = load_config(path);
    const std::string whole = pack_whole(config);
    fs::remove(config.output);
    fs::remove_all(config.work_dir + "/pack");
    fs::remove_all(config.work_dir + "/pack-slabs");
    StageOptions o;
    o.quiet = true;
    for (const char* s : {"0:9", "9:21"}) {
      o.slices = s;
      run_pack_stage(config, o);
    }
    o.slices.clear();
    run_pack_merge(config, o);
    EXPECT_TRUE(read_file(config.output) == whole) << "brick edge " << edge;
  }
}

// A slab file of version 1 (no level-1 slices) is refused with a message naming it and the shard.
TEST_F(PackShards, OldSlabVersionRefused) {
  run_pack_stage(config_, shard("0:12"));
  run_pack_stage(config_, shard("12:24"));
  std::string bytes = read_file(slab(2));
  const std::size_t at = bytes.find("\"version\":3");
  ASSERT_NE(at, std::string::npos);
  bytes[at + 10] = '2';  // version 2: level-1 slices, no crop bounds
  const std::uint64_t sum = xxh64(bytes.data(), bytes.size() - 8);
  std::memcpy(&bytes[bytes.size() - 8], &sum, 8);
  fs::remove(slab(2));
  write_file_atomic(slab(2), bytes);
  std::string message = error_of<InputError>([&] { run_pack_merge(config_, quiet()); });
  EXPECT_NE(message.find("slab_0002.vpkslab: slab file version 2"), std::string::npos) << message;
  EXPECT_NE(message.find("--slices 16:24"), std::string::npos) << message;
  EXPECT_FALSE(fs::exists(config_.output));
}

// A shard narrows the labels to uint8 as it fills its slab (the palette's IDs fit it): an
// intermediate holding an ID above 255 stops the shard with an error naming the slice, the voxel
// and the ID, and writes no slab file for that slab; restored, the shard and merge match again.
TEST_F(PackShards, LabelAboveUint8StopsTheShardNamingSliceAndVoxel) {
  const std::string path = labels_path(config_, 9);
  const std::string original = read_file(path);
  cv::Mat ids = read_slice(path);
  ASSERT_EQ(ids.type(), CV_16UC1);
  ids.at<std::uint16_t>(5, 7) = 300;
  fs::remove(path);
  write_image(path, ids);
  std::string message = error_of<InputError>([&] { run_pack_stage(config_, shard("0:12")); });
  EXPECT_NE(message.find("slice 9"), std::string::npos) << message;
  EXPECT_NE(message.find("voxel (7, 5)"), std::string::npos) << message;
  EXPECT_NE(message.find("label ID 300 does not fit the stored type uint8"), std::string::npos)
      << message;
  EXPECT_TRUE(fs::exists(slab(0))) << "slab 0 (slices 0-7) was whole before slice 9";
  EXPECT_FALSE(fs::exists(slab(1)));
  fs::remove(path);
  write_file_atomic(path, original);
  EXPECT_TRUE(shards_then_merge({"0:12", "12:24"}) == *whole_);
}

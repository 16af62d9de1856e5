// vispack-pack: the packed file's channels against the phantom's truth, metadata, downsampling.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>

#include "packed_compare.h"
#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/nrrd.h"
#include "vispack/format/reader.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/pack/pack.h"
#include "vispack/pipeline/run/run.h"

using namespace vispack;
using namespace vispack::pipeline;
using namespace vispack::phantom;

namespace {

// The intermediates pack reads for slice k, read back from the work folder.
struct Slices {
  cv::Mat rgb, mask, ct, labels;
};
Slices intermediates(const Config& config, int k) {
  char name[32];
  auto path = [&](const char* folder, const char* stem) {
    std::snprintf(name, sizeof name, "%s_%04d.png", stem, k);
    return config.work_dir + "/" + folder + "/" + name;
  };
  Slices s;
  s.rgb = read_slice(path("register/registered", "rgb"));
  s.mask = read_slice(path("mask", "mask"));
  s.ct = read_slice(path("mask", "ct"));
  s.labels = read_slice(path("labels", "labels"));
  EXPECT_EQ(s.rgb.type(), CV_8UC3);
  EXPECT_EQ(s.mask.type(), CV_8UC1);
  EXPECT_EQ(s.ct.type(), CV_16UC1);
  EXPECT_EQ(s.labels.type(), CV_16UC1);
  return s;
}

// The tiny phantom (seed 7) in `dir`; its config.json as written.
nlohmann::json tiny_phantom(const test::TempDir& dir) {
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 7;
  po.quiet = true;
  make_phantom(dir.path(), po);
  return nlohmann::json::parse(read_file(dir / "config.json"));
}

// `dir`'s config.json run through every stage up to the packed file (quiet); its config.
Config run_to_pack(const test::TempDir& dir) {
  Config config = load_config(dir / "config.json");
  RunOptions options;
  options.quiet = true;
  options.to = "pack";
  run_pipeline(config, options);
  return config;
}

}  // namespace

TEST(Pack, MetadataDefectsAndReproducibility) {
  test::TempDir dir;
  tiny_phantom(dir);
  {
    // The full-size registered colour and resampled CT are compared below as the register and
    // mask stages write them (work.write_registered / write_ct; off by default): the stages
    // rebuild them from the inputs, so this also checks that the copies agree.
    auto j = nlohmann::json::parse(read_file(dir / "config.json"));
    j["work"]["write_registered"] = true;
    j["work"]["write_ct"] = true;
    write_file_atomic(dir / "config.json", j.dump());
  }
  const Config config = run_to_pack(dir);

  auto reader = format::Reader::open(config.output);
  const auto dims = reader.dims();
  ASSERT_EQ(dims[0], 96);
  ASSERT_EQ(dims[1], 64);
  ASSERT_EQ(dims[2], 24);
  EXPECT_DOUBLE_EQ(reader.spacing_mm()[0], 0.5);
  const std::size_t n = std::size_t(dims[0]) * dims[1] * dims[2];
  std::vector<std::uint8_t> rgba(n * 4);
  std::vector<std::int16_t> ct(n);
  std::vector<std::uint16_t> labels(n);
  reader.read_region("rgba", 0, 0, 0, 0, dims[0], dims[1], dims[2], rgba.data());
  reader.read_region("ct", 0, 0, 0, 0, dims[0], dims[1], dims[2], ct.data());
  int label_channel = reader.channel_index("labels");
  ASSERT_EQ(reader.channels()[label_channel].type, format::ChannelType::kUint8);  // IDs <= 9
  std::vector<std::uint8_t> labels8(n);
  reader.read_region(label_channel, 0, 0, 0, 0, dims[0], dims[1], dims[2], labels8.data());

  // Agreement of the channels with truth/ is tested on the small phantom, with tolerances
  // derived from the stage goals, in test_truth.cpp (the tiny phantom is too coarse for that).
  // Here: pack only packs, so every voxel equals the intermediates it read (docs/ARCHITECTURE.md
  // "Work folder layout"): colour = registered slice, alpha = mask, HU = ct png - 32768, labels;
  // outside the body (mask 0) colour 0 and HU -1024 (pack.keep_outside_body default "none").
  auto meta = reader.metadata();
  std::uint64_t wrong_rgba = 0, wrong_ct = 0, wrong_labels = 0, body = 0;
  for (int k = 0; k < dims[2]; ++k) {
    const Slices s = intermediates(config, k);
    for (int y = 0; y < dims[1]; ++y)
      for (int x = 0; x < dims[0]; ++x) {
        const std::size_t i = (std::size_t(k) * dims[1] + y) * dims[0] + x;
        const std::uint8_t a = s.mask.at<std::uint8_t>(y, x);
        const cv::Vec3b c = a ? s.rgb.at<cv::Vec3b>(y, x) : cv::Vec3b(0, 0, 0);
        body += a != 0;
        if (rgba[4 * i] != c[0] || rgba[4 * i + 1] != c[1] || rgba[4 * i + 2] != c[2] ||
            rgba[4 * i + 3] != a)
          ++wrong_rgba;
        if (ct[i] != (a ? int(s.ct.at<std::uint16_t>(y, x)) - 32768 : -1024)) ++wrong_ct;
        if (labels8[i] != s.labels.at<std::uint16_t>(y, x)) ++wrong_labels;
      }
  }
  EXPECT_EQ(wrong_rgba, 0u);
  EXPECT_EQ(wrong_ct, 0u);
  EXPECT_EQ(wrong_labels, 0u);
  // The intermediates are not trivial: a body covering 10..90 % of the volume, gel outside.
  EXPECT_GT(body, n / 10);
  EXPECT_LT(body, n * 9 / 10);

  // Metadata: label table from the palette, provenance, slice defects.
  ASSERT_EQ(reader.label_table().size(), 9u);
  EXPECT_EQ(reader.label_table()[0].name, "skin");
  EXPECT_EQ(meta["extra"]["provenance"]["vispack_version"], VISPACK_PROJECT_VERSION);
  EXPECT_EQ(meta["extra"]["provenance"]["input_hashes"]["transforms"].get<std::string>().size(),
            16u);
  EXPECT_EQ(meta["extra"]["slices"]["count"], 24);

  // Byte-reproducible: a forced repack gives the same bytes.
  std::string before = read_file(config.output);
  RunOptions again;
  again.quiet = true;
  again.from = "pack";
  again.to = "pack";
  again.force = true;
  run_pipeline(config, again);
  EXPECT_TRUE(read_file(config.output) == before);

  // Downsampling by 2: dims halve, spacing doubles; alpha and HU are the 2x2 block means of the
  // full-resolution intermediates (within 1 for rounding; HU -1024 outside the body), colour
  // their mask-weighted mean (the plain mean, 0, where the block has no body), labels the block's
  // majority (checked where 3 or 4 of the 4 agree; elsewhere one of the block's IDs).
  auto j = nlohmann::json::parse(read_file(dir / "config.json"));
  j["pack"]["downsample"] = 2;
  write_file_atomic(dir / "config.json", j.dump());
  Config half = load_config(dir / "config.json");
  run_pipeline(half, again);
  auto r2 = format::Reader::open(half.output);
  const auto d2 = r2.dims();
  ASSERT_EQ(d2[0], 48);
  ASSERT_EQ(d2[1], 32);
  ASSERT_EQ(d2[2], 24);
  EXPECT_DOUBLE_EQ(r2.spacing_mm()[0], 1.0);
  EXPECT_DOUBLE_EQ(r2.spacing_mm()[1], 1.0);
  const std::size_t n2 = std::size_t(d2[0]) * d2[1] * d2[2];
  std::vector<std::uint8_t> rgba2(n2 * 4), labels2(n2);
  std::vector<std::int16_t> ct2(n2);
  r2.read_region("rgba", 0, 0, 0, 0, d2[0], d2[1], d2[2], rgba2.data());
  r2.read_region("ct", 0, 0, 0, 0, d2[0], d2[1], d2[2], ct2.data());
  r2.read_region("labels", 0, 0, 0, 0, d2[0], d2[1], d2[2], labels2.data());
  std::uint64_t off_mean = 0, off_ct = 0, off_majority = 0, not_in_block = 0, majorities = 0;
  for (int k = 0; k < d2[2]; ++k) {
    const Slices s = intermediates(config, k);
    for (int y = 0; y < d2[1]; ++y)
      for (int x = 0; x < d2[0]; ++x) {
        const std::size_t i = (std::size_t(k) * d2[1] + y) * d2[0] + x;
        double sum[4] = {0, 0, 0, 0}, hu = 0;
        std::map<int, int> votes;
        for (int dy = 0; dy < 2; ++dy)
          for (int dx = 0; dx < 2; ++dx) {
            const std::uint8_t a = s.mask.at<std::uint8_t>(2 * y + dy, 2 * x + dx);
            const cv::Vec3b c = s.rgb.at<cv::Vec3b>(2 * y + dy, 2 * x + dx);
            for (int ch = 0; ch < 3; ++ch)
              sum[ch] += double(c[ch]) * a;
            sum[3] += a;
            hu += a ? int(s.ct.at<std::uint16_t>(2 * y + dy, 2 * x + dx)) - 32768 : -1024;
            ++votes[s.labels.at<std::uint16_t>(2 * y + dy, 2 * x + dx)];
          }
        for (int ch = 0; ch < 3; ++ch) {
          const double expected = sum[3] > 0 ? sum[ch] / sum[3] : 0.0;
          if (std::abs(rgba2[4 * i + ch] - expected) > 1.0) ++off_mean;
        }
        if (std::abs(rgba2[4 * i + 3] - sum[3] / 4) > 1.0) ++off_mean;
        if (std::abs(ct2[i] - hu / 4) > 1.0) ++off_ct;
        if (!votes.count(labels2[i])) ++not_in_block;
        for (const auto& [id, count] : votes)
          if (count >= 3) {
            ++majorities;
            if (labels2[i] != id) ++off_majority;
          }
      }
  }
  EXPECT_EQ(off_mean, 0u);
  EXPECT_EQ(off_ct, 0u);
  EXPECT_EQ(off_majority, 0u);
  EXPECT_EQ(not_in_block, 0u);
  EXPECT_GT(majorities, n2 / 2);

  // A shard and a merge at once are refused (usage, exit 2); sharding itself is
  // test_pack_shards.cpp.
  std::string out;
  EXPECT_EQ(test::run_command(test::bin("vispack-pack") + " --config " + dir / "config.json" +
                                  " --slices 0:5 --merge",
                              &out),
            2)
      << out;
}

namespace {

// The tiny phantom with the VH female's naming (a number per millimetre, a letter per 1/3 mm
// slice; CT and segmentation on every slot) and 8-slice bricks (three slabs), the colour files
// of stack indices `gone` deleted; run to the packed file (streaming).
Config lettered_tiny_to_pack(const test::TempDir& dir, const std::vector<int>& gone) {
  auto j = tiny_phantom(dir);
  j["spacing_mm"][2] = 1.0 / 3.0;
  j["ct"]["slice_spacing_mm"] = 1.0 / 3.0;
  j["seg"]["slice_spacing_mm"] = 1.0 / 3.0;
  j["rgb"]["pattern"] = "avf{n}{a}.png";
  j["pack"]["brick_edge"] = 8;
  write_file_atomic(dir / "config.json", j.dump());
  const std::string rgb = dir / j["rgb"]["dir"].get<std::string>();
  for (int k = 0; k < 24; ++k) {
    char from[32];
    std::snprintf(from, sizeof from, "/rgb_%04d.png", k);
    const std::string to = "/avf" + std::to_string(1000 + k / 3) + char('a' + k % 3) + ".png";
    if (std::find(gone.begin(), gone.end(), k) != gone.end())
      std::filesystem::remove(rgb + from);
    else
      std::filesystem::rename(rgb + from, rgb + to);
  }
  return run_to_pack(dir);
}

}  // namespace

// A missing letter is a missing slice like a missing number, listed by name in the metadata's
// slices.missing_slices (missing_numbers lists only the numbers none of whose slices is there),
// and each is an empty slice of the volume at its own z: the volume keeps the complete stack's
// depth and every other slice lies at the complete stack's z, whether packed by the streaming
// run, by vispack-pack or by shards and a merge (docs/ARCHITECTURE.md "Each input at its own z").
TEST(Pack, MissingLettersAndNumbersAreListed) {
  test::TempDir dir, whole_dir;
  // Deleted: 1002b (k = 7) and the whole of 1005 (k = 15, 16, 17).
  const std::vector<int> gone = {7, 15, 16, 17};
  const Config config = lettered_tiny_to_pack(dir, gone);
  const Config whole = lettered_tiny_to_pack(whole_dir, {});
  auto reader = format::Reader::open(config.output);
  EXPECT_EQ(reader.dims()[2], 24);
  const auto slices = reader.metadata()["extra"]["slices"];
  EXPECT_EQ(slices["count"], 20);
  EXPECT_EQ(slices["depth"], 24);
  EXPECT_EQ(slices["missing_numbers"], nlohmann::json::array({1005}));
  EXPECT_EQ(slices["missing_slices"], nlohmann::json::array({"1002b", "1005a", "1005b", "1005c"}));
  EXPECT_EQ(slices["missing_z"], nlohmann::json::array({7, 15, 16, 17}));
  const auto report =
      nlohmann::json::parse(read_file(config.work_dir + "/pack/report.json"))["quality"];
  EXPECT_EQ(report["missing_slices"], 4);
  EXPECT_EQ(nlohmann::json::parse(read_file(config.work_dir + "/pack/report.json"))["dims"][2], 24);

  // Slice by slice against the complete stack at the same z (the registration solve loses the
  // pairs across the gaps: the bodies move by a fraction of a pixel, the CT is the same).
  const test::PackedLevel0 gap_volume = test::read_packed_level0(config.output);
  const test::PackedLevel0 whole_volume = test::read_packed_level0(whole.output);
  test::expect_gaps_at_their_z(gap_volume, whole_volume, gone, 0.97, 0.97, 0.97);

  // vispack-pack (staged), and shards of the stack then the merge: the same file byte for byte.
  // The shards name stack indices: 0:8, 8:14 and 14:20 cover output z [0, 9), [9, 18) and
  // [18, 24), so the first packs slabs 0 and 1 (starts 0 and 8), the second slab 2 (its start 16
  // an empty slot), the third none.
  const std::string streamed = read_file(config.output);
  std::vector<int> slabs_packed;
  auto again = [&](const std::vector<std::string>& shards) {
    std::filesystem::remove(config.output);
    std::filesystem::remove_all(config.work_dir + "/pack");
    std::filesystem::remove_all(config.work_dir + "/pack-slabs");
    StageOptions o;
    o.quiet = true;
    for (const auto& range : shards) {
      o.slices = range;
      slabs_packed.push_back(run_pack_stage(config, o).processed);
    }
    o.slices.clear();
    if (shards.empty())
      run_pack_stage(config, o);
    else
      run_pack_merge(config, o);
    return read_file(config.output);
  };
  EXPECT_TRUE(again({}) == streamed) << "vispack-pack differs from the streaming run";
  EXPECT_TRUE(again({"14:20", "0:8", "8:14"}) == streamed) << "shards and merge differ";
  EXPECT_EQ(slabs_packed, (std::vector<int>{0, 2, 1}));
}

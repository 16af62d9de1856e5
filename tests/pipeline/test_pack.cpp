// vispack-pack: the packed file's channels against the phantom's truth, metadata, downsampling.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/nrrd.h"
#include "vispack/format/reader.h"
#include "vispack/pipeline/phantom.h"
#include "vispack/pipeline/run.h"

using namespace vispack;
using namespace vispack::pipeline;

TEST(Pack, MetadataDefectsAndReproducibility) {
  test::TempDir dir;
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 7;
  po.quiet = true;
  make_phantom(dir.path(), po);
  Config config = load_config(dir / "config.json");
  RunOptions options;
  options.quiet = true;
  options.to = "pack";
  run_pipeline(config, options);

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
  auto meta = reader.metadata();
  EXPECT_GT(std::count(labels8.begin(), labels8.end(), 0), 0);  // gel stays unlabelled
  EXPECT_GT(std::count_if(rgba.begin(), rgba.end(), [](std::uint8_t v) { return v != 0; }), 0);
  EXPECT_GT(std::count_if(ct.begin(), ct.end(), [](std::int16_t hu) { return hu > 0; }), 0);

  // Metadata: label table from the palette, provenance, slice defects.
  ASSERT_EQ(reader.label_table().size(), 9u);
  EXPECT_EQ(reader.label_table()[0].name, "skin");
  EXPECT_EQ(meta["extra"]["provenance"]["vispack_version"], "0.1.0");
  EXPECT_EQ(meta["extra"]["provenance"]["input_hashes"]["transforms"].get<std::string>().size(),
            16u);
  EXPECT_EQ(meta["extra"]["slices"]["count"], 24);

  // Byte-reproducible: a forced repack gives the same bytes.
  std::string before = read_file(config.output);
  RunOptions again = options;
  again.from = "pack";
  again.force = true;
  run_pipeline(config, again);
  EXPECT_TRUE(read_file(config.output) == before);

  // Downsampling by 2: dims halve (rounding up), labels stay IDs of the table.
  auto j = nlohmann::json::parse(read_file(dir / "config.json"));
  j["pack"]["downsample"] = 2;
  write_file_atomic(dir / "config.json", j.dump());
  Config half = load_config(dir / "config.json");
  run_pipeline(half, again);
  auto r2 = format::Reader::open(half.output);
  EXPECT_EQ(r2.dims()[0], 48);
  EXPECT_EQ(r2.dims()[1], 32);
  EXPECT_DOUBLE_EQ(r2.spacing_mm()[0], 1.0);

  std::string out;
  EXPECT_EQ(
      test::run_command(
          test::bin("vispack-pack") + " --config " + dir / "config.json" + " --slices 0:5", &out),
      2)
      << out;
}

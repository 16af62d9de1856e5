// vispack-vdb: vdb_print lists the three grids; reading back with OpenVDB gives the values of the
// intermediates, active only inside the mask, with the anisotropic voxel size. Under a memory
// budget (vdb.max_memory_mb) it exports the finest level that fits, with the values and voxel
// size of the packed file's level; an explicit vdb.level over the budget is a ConfigError.
#include <gtest/gtest.h>

#include <sys/resource.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstring>
#include <filesystem>
#include <map>
#include <set>
#include <thread>
#include <tuple>

#include <openvdb/openvdb.h>
#include <tbb/parallel_for.h>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/format/reader.h"
#include "vispack/format/writer.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/run/run.h"
#include "vispack/pipeline/vdb/vdb.h"
#include "vispack/pipeline/vdb/vdb_level.h"
#include "vispack/pipeline/vdb/vdb_write.h"

using namespace vispack;
using namespace vispack::pipeline;
using namespace vispack::phantom;
namespace fs = std::filesystem;

namespace {

// The tiny phantom (96 x 64 x 24) the export tests run on.
void make_tiny_phantom(const std::string& dir) {
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 6;
  po.quiet = true;
  make_phantom(dir, po);
}

}  // namespace

TEST(Vdb, GridsValuesAndVdbPrint) {
  test::TempDir dir;
  make_tiny_phantom(dir.path());
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
  // The default budget exports level 0 of a small volume and says so in the report.
  auto report = nlohmann::json::parse(read_file(config.work_dir + "/vdb/report.json"));
  EXPECT_EQ(report["level"], 0);
  EXPECT_EQ(report["level_choice"], "auto");

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
  // Command line: a range that is not one is a usage error.
  EXPECT_EQ(
      test::run_command(
          test::bin("vispack-vdb") + " --config " + dir / "config.json" + " --slices 5:2", &out),
      2)
      << out;
}

namespace {

// Every active voxel of `grid` with its value, by coordinate.
template <class GridT>
std::map<std::array<int, 3>, typename GridT::ValueType> active_voxels(const GridT& grid) {
  std::map<std::array<int, 3>, typename GridT::ValueType> out;
  for (auto it = grid.cbeginValueOn(); it; ++it) {
    if (!it.isVoxelValue()) {
      ADD_FAILURE() << "a tile in the exported grid (the export sets voxels only)";
      continue;
    }
    const openvdb::Coord c = it.getCoord();
    out[{c.x(), c.y(), c.z()}] = *it;
  }
  return out;
}

template <class GridT>
typename GridT::Ptr read_grid(const std::string& path, const std::string& name) {
  openvdb::io::File file(path);
  file.open();
  auto grid = openvdb::gridPtrCast<GridT>(file.readGrid(name));
  file.close();
  return grid;
}

// The voxels of a set of part files, gathered: each voxel must lie in its part's level z range
// [z0, z1) and in one part only.
struct GatheredParts {
  std::map<std::array<int, 3>, openvdb::Vec3s> rgb;
  std::map<std::array<int, 3>, float> ct;
  std::map<std::array<int, 3>, int> labels;
  std::size_t voxels = 0;
  void add(const std::string& path, const openvdb::Vec3SGrid& part_rgb, int z0, int z1) {
    for (const auto& [c, v] : active_voxels(part_rgb)) {
      EXPECT_TRUE(c[2] >= z0 && c[2] < z1) << "voxel z " << c[2] << " outside the part " << path;
      EXPECT_TRUE(rgb.emplace(c, v).second) << "voxel in two parts";
      ++voxels;
    }
    for (const auto& [c, v] : active_voxels(*read_grid<openvdb::FloatGrid>(path, "ct")))
      ct.emplace(c, v);
    for (const auto& [c, v] : active_voxels(*read_grid<openvdb::Int32Grid>(path, "labels")))
      labels.emplace(c, v);
  }
};

}  // namespace

// Shards (--slices A:B) export parts that tile the unsharded export exactly, at level 0 and at
// a coarser level whose z boundaries fall inside bricks and between slices (24 slices: shards
// 0:7, 7:16, 16:24 at level 1 cover level z [0, 4), [4, 8), [8, 12)); each part is named for its
// slices, says its ranges, and resumes on its own.
TEST(Vdb, ShardsTileTheWholeExport) {
  test::TempDir dir;
  make_tiny_phantom(dir.path());
  for (int level : {0, 1}) {
    SCOPED_TRACE("level " + std::to_string(level));
    auto j = nlohmann::json::parse(read_file(dir / "config.json"));
    j["vdb"]["level"] = level;
    write_file_atomic(dir / "config.json", j.dump());
    Config config = load_config(dir / "config.json");
    RunOptions options;
    options.quiet = true;
    options.force = level == 1;
    run_pipeline(config, options);
    openvdb::initialize();
    const auto whole_rgb = active_voxels(*read_grid<openvdb::Vec3SGrid>(config.vdb_output, "rgb"));
    const auto whole_ct = active_voxels(*read_grid<openvdb::FloatGrid>(config.vdb_output, "ct"));
    const auto whole_labels =
        active_voxels(*read_grid<openvdb::Int32Grid>(config.vdb_output, "labels"));
    ASSERT_GT(whole_rgb.size(), 500u);

    GatheredParts gathered;
    const std::vector<std::tuple<int, int, std::string>> shards = {
        {0, 7, "0000-0007"}, {7, 16, "0007-0016"}, {16, 24, "0016-0024"}};
    for (const auto& [a, b, digits] : shards) {
      StageOptions so;
      so.quiet = true;
      so.slices = std::to_string(a) + ":" + std::to_string(b);
      StageResult r = run_vdb_stage(config, so);
      EXPECT_EQ(r.processed, 1);
      const std::string path = vdb_part_path(config, a, b);
      EXPECT_EQ(r.output, path);
      EXPECT_EQ(fs::path(path).filename().string(),
                fs::path(config.vdb_output).stem().string() + ".slices-" + digits + ".vdb");
      auto rgb = read_grid<openvdb::Vec3SGrid>(path, "rgb");
      ASSERT_TRUE(rgb);
      EXPECT_EQ(rgb->metaValue<std::string>("vispack_part_slices"),
                std::to_string(a) + ":" + std::to_string(b));
      const int div = 1 << level;
      const int z0 = (a + div - 1) / div, z1 = (b + div - 1) / div;
      EXPECT_EQ(rgb->metaValue<std::string>("vispack_part_z"),
                std::to_string(z0) + ":" + std::to_string(z1));
      gathered.add(path, *rgb, z0, z1);
      // Up to date on a rerun; the part file alone was written (vdb_output untouched).
      EXPECT_EQ(run_vdb_stage(config, so).processed, 0);
    }
    EXPECT_EQ(gathered.voxels, whole_rgb.size());
    EXPECT_TRUE(gathered.rgb == whole_rgb) << "the parts' colour differs from the whole export";
    EXPECT_TRUE(gathered.ct == whole_ct) << "the parts' CT differs from the whole export";
    EXPECT_TRUE(gathered.labels == whole_labels)
        << "the parts' labels differ from the whole export";
  }
}

// Colour files 7, 15, 16 and 17 missing: the packed volume keeps the stack's full depth (each
// missing file an empty slice at its z, docs/ARCHITECTURE.md "Each input at its own z"), the
// export has active voxels exactly on the slices the packed alpha has body at the same z, and
// shards named by stack indices export parts named by the output z they cover that tile it.
TEST(Vdb, AStackWithMissingColourFilesKeepsItsDepthAndShardsTileIt) {
  test::TempDir dir;
  make_tiny_phantom(dir.path());
  auto j = nlohmann::json::parse(read_file(dir / "config.json"));
  j["ct"]["slice_spacing_mm"] = j["spacing_mm"][2];  // segmentation paired by z, not by number
  j["seg"]["slice_spacing_mm"] = j["spacing_mm"][2];
  write_file_atomic(dir / "config.json", j.dump());
  const Config config = load_config(dir / "config.json");
  const std::vector<int> gone = {7, 15, 16, 17};
  for (int k : gone) {
    char name[32];
    std::snprintf(name, sizeof name, "/rgb_%04d.png", k);
    ASSERT_TRUE(fs::remove(config.rgb.dir + name));
  }
  RunOptions options;
  options.quiet = true;
  run_pipeline(config, options);
  const format::Reader packed = format::Reader::open(config.output);
  ASSERT_EQ(packed.dims()[2], 24);
  const std::vector<std::uint8_t> rgba = packed.read_level("rgba", 0);
  const std::size_t plane = std::size_t(packed.dims()[0]) * std::size_t(packed.dims()[1]);
  std::set<int> body_z;
  for (std::size_t i = 0; i < rgba.size() / 4; ++i)
    if (rgba[4 * i + 3] > 0) body_z.insert(int(i / plane));
  for (int z : gone)
    EXPECT_EQ(body_z.count(z), 0u) << "body in the empty slice " << z;
  EXPECT_EQ(body_z.count(23), 1u) << "no body on the last file's slice (z 23)";
  openvdb::initialize();
  const auto whole_rgb = active_voxels(*read_grid<openvdb::Vec3SGrid>(config.vdb_output, "rgb"));
  std::set<int> active_z;
  for (const auto& [c, v] : whole_rgb)
    active_z.insert(c[2]);
  EXPECT_EQ(active_z, body_z) << "the export's slices are not the packed volume's";

  GatheredParts gathered;
  const std::vector<std::tuple<std::string, int, int>> shards = {
      {"0:7", 0, 8}, {"7:13", 8, 14}, {"13:20", 14, 24}};  // stack indices, output z
  for (const auto& [slices, z0, z1] : shards) {
    StageOptions so;
    so.quiet = true;
    so.slices = slices;
    const StageResult r = run_vdb_stage(config, so);
    EXPECT_EQ(r.output, vdb_part_path(config, z0, z1)) << slices;
    auto rgb = read_grid<openvdb::Vec3SGrid>(r.output, "rgb");
    ASSERT_TRUE(rgb) << r.output;
    gathered.add(r.output, *rgb, z0, z1);
  }
  EXPECT_EQ(gathered.voxels, whole_rgb.size());
  EXPECT_TRUE(gathered.rgb == whole_rgb) << "the parts' colour differs from the whole export";
}

// The grids are built on several threads, each from a run of bricks, then merged: the trees are
// those of a one-thread build (same active voxels and values, same leaves, same file size).
TEST(Vdb, ThreadsBuildTheGridsOfOneThread) {
  test::TempDir dir;
  make_tiny_phantom(dir.path());
  Config config = load_config(dir / "config.json");
  RunOptions options;
  options.quiet = true;
  options.to = "pack";
  run_pipeline(config, options);
  openvdb::initialize();
  std::map<int, std::uintmax_t> file_bytes;
  std::map<int, openvdb::Vec3SGrid::Ptr> rgb;
  std::map<int, openvdb::FloatGrid::Ptr> ct;
  std::map<int, openvdb::Int32Grid::Ptr> labels;
  for (int threads : {1, 3}) {
    StageOptions so;
    so.quiet = true;
    so.force = true;
    so.threads = threads;
    StageResult r = run_vdb_stage(config, so);
    ASSERT_EQ(r.processed, 1);
    file_bytes[threads] = fs::file_size(config.vdb_output);
    rgb[threads] = read_grid<openvdb::Vec3SGrid>(config.vdb_output, "rgb");
    ct[threads] = read_grid<openvdb::FloatGrid>(config.vdb_output, "ct");
    labels[threads] = read_grid<openvdb::Int32Grid>(config.vdb_output, "labels");
    ASSERT_TRUE(rgb[threads] && ct[threads] && labels[threads]);
  }
  const auto one = active_voxels(*rgb[1]);
  ASSERT_GT(one.size(), 500u);
  EXPECT_TRUE(active_voxels(*rgb[3]) == one);
  EXPECT_TRUE(active_voxels(*ct[3]) == active_voxels(*ct[1]));
  EXPECT_TRUE(active_voxels(*labels[3]) == active_voxels(*labels[1]));
  EXPECT_EQ(rgb[3]->tree().leafCount(), rgb[1]->tree().leafCount());
  EXPECT_TRUE(rgb[3]->tree().hasSameTopology(rgb[1]->tree()));
  EXPECT_TRUE(ct[3]->tree().hasSameTopology(ct[1]->tree()));
  EXPECT_TRUE(labels[3]->tree().hasSameTopology(labels[1]->tree()));
  EXPECT_EQ(file_bytes[3], file_bytes[1]);
}

// The threads this process has now (TBB's workers, once started, stay until exit).
int process_threads() {
  int count = 0;
  for ([[maybe_unused]] const auto& entry : fs::directory_iterator("/proc/self/task"))
    ++count;
  return count;
}

// --threads 1 is one thread, OpenVDB's own TBB loops included (its write computes per-leaf
// metadata in a TBB loop, which would otherwise take a TBB worker per core): the export starts
// no thread that outlives it. TBB starts a worker when a loop asks for one, from the thread that
// asks, and keeps it, so a worker the export asked for (during the run, or one that a lifted
// limit lets through after it) is still counted when the stage returns. The phantom and its
// packed file are made by child processes (nothing of theirs runs in this one). (On a one-core
// machine TBB has no worker either way.)
TEST(Vdb, OneThreadRunsNoTbbWorker) {
  test::TempDir dir;
  ASSERT_EQ(test::run_command(test::bin("vispack-phantom") + " --out " + dir.path() +
                              " --preset tiny --seed 6 --quiet"),
            0);
  ASSERT_EQ(test::run_command(test::bin("vispack-run") + " " + dir / "config.json" +
                              " --to pack --quiet --threads 1"),
            0);
  Config config = load_config(dir / "config.json");
  openvdb::initialize();
  const int before = process_threads();
  StageOptions so;
  so.quiet = true;
  so.threads = 1;
  EXPECT_EQ(run_vdb_stage(config, so).processed, 1);
  EXPECT_EQ(process_threads(), before);
  // The count does see a TBB worker when TBB has one to give (else this test could not fail):
  // two iterations that wait for each other, so a worker must take the second.
  if (std::thread::hardware_concurrency() >= 2) {
    std::atomic<int> arrived{0};
    tbb::parallel_for(0, 2, [&](int) {
      ++arrived;
      const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(30);
      while (arrived.load() < 2 && std::chrono::steady_clock::now() < until)
        std::this_thread::yield();
    });
    EXPECT_GT(process_threads(), before);
  }
}

// Bricks of whole leaves (edge a multiple of 8, every edge a config allows) fill OpenVDB leaves
// directly; a packed file of edge 4 (the format allows it) is exported voxel by voxel through an
// accessor. The level-0 voxels do not depend on the brick edge, so both give the same grids.
TEST(Vdb, LeafFillingEqualsVoxelByVoxel) {
  test::TempDir dir;
  make_tiny_phantom(dir.path());
  auto j = nlohmann::json::parse(read_file(dir / "config.json"));
  j["vdb"]["level"] = 0;
  write_file_atomic(dir / "config.json", j.dump());
  Config config = load_config(dir / "config.json");
  RunOptions options;
  options.quiet = true;
  run_pipeline(config, options);
  openvdb::initialize();
  struct Grids {
    std::map<std::array<int, 3>, openvdb::Vec3s> rgb;
    std::map<std::array<int, 3>, float> ct;
    std::map<std::array<int, 3>, int> labels;
    openvdb::Index64 leaves = 0;
  };
  auto read_all = [&] {
    Grids g;
    auto rgb = read_grid<openvdb::Vec3SGrid>(config.vdb_output, "rgb");
    EXPECT_TRUE(rgb);
    if (!rgb) return g;
    g.rgb = active_voxels(*rgb);
    g.leaves = rgb->tree().leafCount();
    g.ct = active_voxels(*read_grid<openvdb::FloatGrid>(config.vdb_output, "ct"));
    g.labels = active_voxels(*read_grid<openvdb::Int32Grid>(config.vdb_output, "labels"));
    return g;
  };
  const Grids by_leaves = read_all();
  {
    // The same level 0 repacked with 4^3 bricks.
    const format::Reader packed = format::Reader::open(config.output);
    ASSERT_EQ(packed.brick_edge() % 8, 0);
    format::WriterOptions o;
    o.dims = packed.dims(0);
    o.spacing_mm = packed.spacing_mm(0);
    o.origin_mm = packed.origin_mm(0);
    o.brick_edge = 4;
    o.label_table = packed.label_table();
    std::vector<std::vector<std::uint8_t>> levels;
    for (std::size_t c = 0; c < packed.channels().size(); ++c) {
      format::ChannelSpec spec = packed.channels()[c];
      if (spec.name == "labels") spec.type = format::ChannelType::kUint16;  // passed as uint16
      o.channels.push_back(spec);
      levels.push_back(packed.read_level(int(c), 0));
    }
    const std::size_t plane = std::size_t(o.dims[0]) * std::size_t(o.dims[1]);
    const int labels_c = packed.channel_index("labels");
    const std::size_t label_bytes =
        format::channel_type_bytes(packed.channels()[std::size_t(labels_c)].type);
    std::vector<std::uint16_t> ids(plane);
    format::Writer writer(config.output + ".edge4", o);
    for (std::int64_t z = 0; z < o.dims[2]; ++z) {
      std::vector<const void*> slices;
      for (std::size_t c = 0; c < levels.size(); ++c) {
        const std::size_t bytes = format::channel_type_bytes(packed.channels()[c].type);
        const std::uint8_t* slice = levels[c].data() + std::size_t(z) * plane * bytes;
        if (int(c) == labels_c && label_bytes == 1) {
          for (std::size_t i = 0; i < plane; ++i)
            ids[i] = slice[i];
          slices.push_back(ids.data());
        } else {
          slices.push_back(slice);
        }
      }
      writer.append_slice(slices);
    }
    writer.finish();
  }
  fs::rename(config.output + ".edge4", config.output);
  StageOptions so;
  so.quiet = true;
  so.force = true;
  ASSERT_EQ(run_vdb_stage(config, so).processed, 1);
  const Grids by_voxels = read_all();
  ASSERT_GT(by_leaves.rgb.size(), 500u);
  EXPECT_TRUE(by_voxels.rgb == by_leaves.rgb);
  EXPECT_TRUE(by_voxels.ct == by_leaves.ct);
  EXPECT_TRUE(by_voxels.labels == by_leaves.labels);
  EXPECT_EQ(by_voxels.leaves, by_leaves.leaves);
}

// write_vdb_grids gives the bytes of OpenVDB's own io::File::write (all but the file's random
// UUID), on the background thread or not, with buffers small enough that the archive's seeks
// back to its grid offsets cross buffer boundaries; the file reads back with io::File.
TEST(VdbWrite, BytesOfOpenVdbsFileWriter) {
  test::TempDir dir;
  openvdb::initialize();
  auto ct = openvdb::FloatGrid::create(-1024.0f);
  auto rgb = openvdb::Vec3SGrid::create(openvdb::Vec3s(0, 0, 0));
  auto ct_acc = ct->getAccessor();
  auto rgb_acc = rgb->getAccessor();
  for (int z = 0; z < 40; ++z)
    for (int y = 0; y < 50; ++y)
      for (int x = 0; x < 60; ++x)
        if ((x - 30) * (x - 30) + (y - 25) * (y - 25) < 400 + 10 * z) {
          ct_acc.setValue({x, y, z}, float((x * 7 + y * 3 + z) % 1500 - 500));
          rgb_acc.setValue({x, y, z}, openvdb::Vec3s(x / 60.0f, y / 50.0f, z / 40.0f));
        }
  ct->setName("ct");
  rgb->setName("rgb");
  openvdb::MetaMap meta;
  meta.insertMeta("vispack_test", openvdb::StringMetadata("bytes"));
  openvdb::GridPtrVec grids{ct, rgb};
  const std::string reference = dir / "reference.vdb";
  {
    openvdb::io::File file(reference);
    file.write(grids, meta);
    file.close();
  }
  const std::string expected = read_file(reference);
  ASSERT_GT(expected.size(), 100000u);
  // The header: magic (8), file version (4), library version (4 + 4), grid offsets flag (1),
  // then the 36-character UUID.
  const std::size_t uuid = 21, uuid_end = 57;
  for (bool background : {false, true})
    for (std::size_t buffer : {std::size_t(4096), std::size_t(8) << 20}) {
      SCOPED_TRACE(std::string(background ? "background" : "inline") + ", buffer " +
                   std::to_string(buffer));
      const std::string path = dir / "ours.vdb";
      write_vdb_grids(path, openvdb::GridCPtrVec(grids.begin(), grids.end()), meta, background,
                      buffer);
      const std::string got = read_file(path);
      ASSERT_EQ(got.size(), expected.size());
      EXPECT_EQ(got.substr(0, uuid), expected.substr(0, uuid));
      EXPECT_TRUE(got.compare(uuid_end, std::string::npos, expected, uuid_end) == 0)
          << "bytes after the UUID differ";
      EXPECT_NE(got.substr(uuid, uuid_end - uuid), expected.substr(uuid, uuid_end - uuid))
          << "the UUID is not where this test expects it";
      auto back = read_grid<openvdb::FloatGrid>(path, "ct");
      ASSERT_TRUE(back);
      EXPECT_TRUE(active_voxels(*back) == active_voxels(*ct));
    }
}

// A write that fails (RLIMIT_FSIZE: EFBIG, as a full disk) is an IoError naming the file, on
// the background thread too, and leaves no file behind; in a child process.
TEST(VdbWrite, FailingWriteIsIoErrorNamingTheFile) {
  GTEST_FLAG_SET(death_test_style, "threadsafe");
  test::TempDir dir;
  openvdb::initialize();
  auto grid = openvdb::FloatGrid::create(0.0f);
  auto acc = grid->getAccessor();
  std::uint32_t state = 1;
  for (int z = 0; z < 64; ++z)
    for (int y = 0; y < 64; ++y)
      for (int x = 0; x < 64; ++x) {
        state = state * 1664525u + 1013904223u;  // noise: the grid does not compress away
        acc.setValue({x, y, z}, float(state >> 8));
      }
  grid->setName("noise");
  const openvdb::GridCPtrVec grids{grid};
  const std::string path = dir / "full_disk.vdb";
  for (bool background : {false, true}) {
    EXPECT_EXIT(
        {
          std::signal(SIGXFSZ, SIG_IGN);
          struct rlimit limit {};
          getrlimit(RLIMIT_FSIZE, &limit);
          limit.rlim_cur = 200 * 1024;
          setrlimit(RLIMIT_FSIZE, &limit);
          try {
            write_vdb_grids(path, grids, openvdb::MetaMap(), background, 4096);
            std::_Exit(4);  // wrote past the limit: the test is broken
          } catch (const IoError& e) {
            std::_Exit(std::string(e.what()).find("full_disk.vdb") == std::string::npos ? 3 : 0);
          }
        },
        ::testing::ExitedWithCode(0), "")
        << (background ? "background" : "inline");
    EXPECT_FALSE(fs::exists(path));
  }
}

namespace {

double mib(double bytes) {
  return bytes / (1024.0 * 1024.0);
}

// The small phantom (256 x 192 x 64) run once through pack; each test writes its own config
// variant next to it (same work folder and packed file).
class VdbLevels : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TempDir;
    PhantomOptions po;
    po.preset = "small";
    po.seed = 3;
    po.quiet = true;
    make_phantom(dir_->path(), po);
    Config config = load_config(*dir_ / "config.json");
    RunOptions options;
    options.quiet = true;
    run_pipeline(config, options);
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  // The phantom's config with "vdb" replaced and vdb_output `name`.
  static Config config_with(const nlohmann::json& vdb, const std::string& name) {
    auto j = nlohmann::json::parse(read_file(*dir_ / "config.json"));
    j["vdb"] = vdb;
    j["vdb_output"] = "out/" + name;
    const std::string path = *dir_ / (name + ".json");
    write_file_atomic(path, j.dump());
    return load_config(path);
  }
  static test::TempDir* dir_;
};
test::TempDir* VdbLevels::dir_ = nullptr;

// A budget (MiB) that holds about a third of level 0's leaves per part: level 0 is over it.
std::int64_t third_of_level_zero_mb(const format::Reader& reader) {
  const VdbLevelEstimate e = estimate_vdb_level(reader, 0, 2);
  const std::int64_t budget = std::int64_t(
      std::ceil(mib(kVdbFixedBytes + double(e.leaves) * vdb_bytes_per_leaf(reader) / 3)));
  EXPECT_LT(double(budget), mib(e.bytes)) << "level 0 would fit as one file";
  return budget;
}

StageOptions quiet_stage() {
  StageOptions o;
  o.quiet = true;
  return o;
}

}  // namespace

// The estimate counts exactly the leaves and active voxels the export then builds.
TEST_F(VdbLevels, EstimateCountsTheLeavesTheExportBuilds) {
  Config config = config_with({{"level", 0}}, "l0.vdb");
  run_vdb_stage(config, quiet_stage());
  const format::Reader reader = format::Reader::open(config.output);
  const VdbLevelEstimate e = estimate_vdb_level(reader, 0, 2);
  openvdb::initialize();
  openvdb::io::File file(config.vdb_output);
  file.open(/*delayLoad=*/false);  // leaf buffers in memory, as the export held them
  auto rgb = openvdb::gridPtrCast<openvdb::Vec3SGrid>(file.readGrid("rgb"));
  ASSERT_TRUE(rgb);
  auto ct = openvdb::gridPtrCast<openvdb::FloatGrid>(file.readGrid("ct"));
  auto labels = openvdb::gridPtrCast<openvdb::Int32Grid>(file.readGrid("labels"));
  file.close();
  ASSERT_TRUE(ct);
  ASSERT_TRUE(labels);
  EXPECT_TRUE(e.exact);
  EXPECT_EQ(e.leaves, rgb->tree().leafCount());
  EXPECT_EQ(e.active_voxels, rgb->activeVoxelCount());
  EXPECT_GT(e.leaves, 500u);
  // The estimate against the memory OpenVDB itself reports for the grids the export built (not
  // against the estimate's own formula): its per-leaf part within 5 % of the leaves' bytes, and
  // the fixed allowance above everything else the trees hold (internal nodes, tables).
  std::uint64_t leaf_bytes = 0, grid_bytes = 0;
  auto measure = [&](const auto& grid) {
    for (auto leaf = grid->tree().cbeginLeaf(); leaf; ++leaf)
      leaf_bytes += leaf->memUsage();
    grid_bytes += grid->memUsage();
  };
  measure(rgb);
  measure(ct);
  measure(labels);
  const double leaf_estimate = e.bytes - kVdbFixedBytes - double(e.mapped_bytes);
  std::printf("vdb estimate: leaves %.0f bytes estimated, %llu measured (%.3fx); trees %llu\n",
              leaf_estimate, static_cast<unsigned long long>(leaf_bytes),
              leaf_estimate / double(leaf_bytes), static_cast<unsigned long long>(grid_bytes));
  EXPECT_NEAR(leaf_estimate / double(leaf_bytes), 1.0, 0.05);
  EXPECT_LT(double(grid_bytes - leaf_bytes), kVdbFixedBytes);
}

// A budget between the estimates of levels 1 and 0 chooses level 1; one between 2 and 1 chooses
// level 2; the stage says which in the report and in the file's metadata.
TEST_F(VdbLevels, TinyBudgetChoosesTheFinestLevelThatFits) {
  const Config base = config_with(nlohmann::json::object(), "auto.vdb");
  const format::Reader reader = format::Reader::open(base.output);
  ASSERT_GE(reader.level_count(), 3);
  // The estimates as choose_vdb_level makes them when it decodes every finer level.
  double e[3];
  std::uint64_t resident = 0;
  for (int l = 0; l < 3; ++l) {
    const VdbLevelEstimate est = estimate_vdb_level(reader, l, 2, 0, resident);
    e[l] = est.bytes;
    resident += est.scanned_bytes;
  }
  for (int want = 1; want <= 2; ++want) {
    // The smallest whole MiB at or above level `want`'s estimate must lie below the finer one's.
    const std::int64_t budget = std::int64_t(std::ceil(mib(e[want])));
    ASSERT_LT(double(budget), mib(e[want - 1])) << "level " << want;
    Config config =
        config_with({{"max_memory_mb", budget}, {"layout", "file"}}, cat("budget", want, ".vdb"));
    const VdbLevelChoice choice = choose_vdb_level(config, reader, 2);
    EXPECT_EQ(choice.level, want);
    EXPECT_TRUE(choice.automatic);
    ASSERT_EQ(choice.estimates.size(), std::size_t(want + 1));
    EXPECT_GT(choice.estimates[std::size_t(want - 1)].bytes, double(budget) * 1024 * 1024);
    EXPECT_LE(choice.chosen().bytes, double(budget) * 1024 * 1024);

    run_vdb_stage(config, quiet_stage());
    auto report = nlohmann::json::parse(read_file(config.work_dir + "/vdb/report.json"));
    EXPECT_EQ(report["level"], want);
    EXPECT_EQ(report["max_memory_mb"], budget);
    openvdb::initialize();
    openvdb::io::File file(config.vdb_output);
    file.open();
    auto meta = file.getMetadata();
    auto grid = file.readGrid("ct");
    file.close();
    EXPECT_EQ((*meta)["vispack_level"]->str(), std::to_string(want));
    EXPECT_EQ(grid->metaValue<int>("vispack_level"), want);
    const auto spacing = reader.spacing_mm(want);
    EXPECT_DOUBLE_EQ(grid->voxelSize()[0], spacing[0]);
    EXPECT_DOUBLE_EQ(grid->voxelSize()[2], spacing[2]);
  }
}

// The grids at level L hold exactly the packed file's level L: active where alpha > 0, colour
// c / 255, CT in HU, label IDs; world position of a voxel = the level's origin + index * spacing.
TEST_F(VdbLevels, GridsAtLevelOneHoldThePackedLevel) {
  Config config = config_with({{"level", 1}}, "l1.vdb");
  run_vdb_stage(config, quiet_stage());
  const format::Reader reader = format::Reader::open(config.output);
  const int level = 1;
  const auto dims = reader.dims(level);
  const std::size_t n = std::size_t(dims[0] * dims[1] * dims[2]);
  const std::vector<std::uint8_t> rgba = reader.read_level("rgba", level);
  const std::vector<std::uint8_t> ct = reader.read_level("ct", level);
  const std::vector<std::uint8_t> labels = reader.read_level("labels", level);
  // Labels are stored as uint8 when every ID fits (format::stored_channels_for), else uint16.
  const bool labels16 = reader.channels()[std::size_t(reader.channel_index("labels"))].type ==
                        format::ChannelType::kUint16;

  openvdb::initialize();
  openvdb::io::File file(config.vdb_output);
  file.open();
  auto ct_grid = openvdb::gridPtrCast<openvdb::FloatGrid>(file.readGrid("ct"));
  auto label_grid = openvdb::gridPtrCast<openvdb::Int32Grid>(file.readGrid("labels"));
  auto rgb_grid = openvdb::gridPtrCast<openvdb::Vec3SGrid>(file.readGrid("rgb"));
  file.close();
  ASSERT_TRUE(ct_grid && label_grid && rgb_grid);
  const auto spacing = reader.spacing_mm(level), origin = reader.origin_mm(level);
  EXPECT_DOUBLE_EQ(rgb_grid->voxelSize()[0], spacing[0]);
  EXPECT_DOUBLE_EQ(rgb_grid->voxelSize()[1], spacing[1]);
  EXPECT_DOUBLE_EQ(rgb_grid->voxelSize()[2], spacing[2]);
  const openvdb::Vec3d world = rgb_grid->indexToWorld(openvdb::Coord(3, 5, 7));
  for (int a = 0; a < 3; ++a)
    EXPECT_NEAR(world[a],
                origin[std::size_t(a)] + spacing[std::size_t(a)] * (a == 0   ? 3
                                                                    : a == 1 ? 5
                                                                             : 7),
                1e-9);

  std::uint64_t active = 0;
  for (std::size_t v = 0; v < n; ++v)
    active += rgba[4 * v + 3] > 0;
  EXPECT_EQ(rgb_grid->activeVoxelCount(), active);
  EXPECT_EQ(ct_grid->activeVoxelCount(), active);
  ASSERT_GT(active, 1000u);

  // Every 37th voxel (a few thousand, inside and outside the body), exactly.
  auto ct_acc = ct_grid->getConstAccessor();
  auto lab_acc = label_grid->getConstAccessor();
  auto rgb_acc = rgb_grid->getConstAccessor();
  std::uint64_t checked = 0, inside = 0, wrong = 0;
  for (std::size_t v = 0; v < n; v += 37) {
    const openvdb::Coord ijk(int(v % std::size_t(dims[0])),
                             int(v / std::size_t(dims[0]) % std::size_t(dims[1])),
                             int(v / std::size_t(dims[0] * dims[1])));
    const bool on = rgba[4 * v + 3] > 0;
    ++checked;
    if (rgb_acc.isValueOn(ijk) != on || ct_acc.isValueOn(ijk) != on ||
        lab_acc.isValueOn(ijk) != on) {
      ++wrong;
      continue;
    }
    if (!on) continue;
    ++inside;
    std::int16_t hu;
    std::uint16_t id;
    std::memcpy(&hu, &ct[2 * v], 2);
    id = labels[v];
    if (labels16) std::memcpy(&id, &labels[2 * v], 2);
    const openvdb::Vec3s c = rgb_acc.getValue(ijk);
    if (ct_acc.getValue(ijk) != float(hu) || lab_acc.getValue(ijk) != int(id) ||
        c != openvdb::Vec3s(rgba[4 * v] / 255.0f, rgba[4 * v + 1] / 255.0f,
                            rgba[4 * v + 2] / 255.0f))
      ++wrong;
  }
  EXPECT_GT(inside, 300u);
  EXPECT_GT(checked, 2000u);
  EXPECT_EQ(wrong, 0u);
}

// Over vdb.max_memory_mb as one file, level 0 is written as parts (z slabs, each estimated within
// the budget) whose grids, merged, hold exactly the voxels and values of the one-file export
// (vdb.layout "file"); the index lists them, vdb_output is not written, the report says why; a
// rerun is up to date; back under the budget, one file replaces the parts.
TEST_F(VdbLevels, PartsOverTheBudgetHoldTheOneFileExport) {
  const Config one = config_with({{"level", 0}, {"layout", "file"}}, "one.vdb");
  run_vdb_stage(one, quiet_stage());
  openvdb::initialize();
  const auto whole_rgb = active_voxels(*read_grid<openvdb::Vec3SGrid>(one.vdb_output, "rgb"));
  const auto whole_ct = active_voxels(*read_grid<openvdb::FloatGrid>(one.vdb_output, "ct"));
  const auto whole_labels = active_voxels(*read_grid<openvdb::Int32Grid>(one.vdb_output, "labels"));
  ASSERT_GT(whole_rgb.size(), 10000u);

  const format::Reader reader = format::Reader::open(one.output);
  const std::int64_t budget = third_of_level_zero_mb(reader);
  const Config config = config_with({{"max_memory_mb", budget}}, "parts.vdb");
  const StageResult r = run_vdb_stage(config, quiet_stage());
  const std::string index = vdb_parts_index_path(config);
  EXPECT_EQ(fs::path(index).filename().string(), "parts.parts.json");
  EXPECT_EQ(r.output, index);
  EXPECT_FALSE(fs::exists(config.vdb_output));
  const auto listed = nlohmann::json::parse(read_file(index));
  EXPECT_EQ(listed["level"], 0);
  const auto& parts = listed["parts"];
  ASSERT_GE(parts.size(), 3u);
  const auto dims = reader.dims(0);

  GatheredParts gathered;
  openvdb::Vec3SGrid::Ptr merged;
  std::int64_t next_z = 0;
  for (const auto& p : parts) {
    const std::int64_t z0 = p["z"][0], z1 = p["z"][1];
    EXPECT_EQ(z0, next_z) << "the parts do not tile the level";
    EXPECT_EQ(z0 % 8, 0) << "a part boundary inside a leaf";
    EXPECT_LE(p["estimated_mb"].get<double>(), double(budget));
    next_z = z1;
    const std::string path = fs::path(index).parent_path() / p["file"].get<std::string>();
    const int a = p["slices"][0], b = p["slices"][1];
    EXPECT_EQ(path, vdb_part_path(config, a, b));
    auto rgb = read_grid<openvdb::Vec3SGrid>(path, "rgb");
    ASSERT_TRUE(rgb) << path;
    EXPECT_EQ(rgb->metaValue<std::string>("vispack_part_z"), cat(z0, ":", z1));
    EXPECT_EQ(rgb->metaValue<int>("vispack_level"), 0);
    gathered.add(path, *rgb, int(z0), int(z1));
    // OpenVDB's own merge of the parts (as a user would open them).
    if (!merged)
      merged = rgb;
    else
      merged->tree().merge(rgb->tree(), openvdb::MERGE_ACTIVE_STATES);
  }
  EXPECT_EQ(next_z, dims[2]);
  EXPECT_EQ(gathered.voxels, whole_rgb.size());
  EXPECT_TRUE(gathered.rgb == whole_rgb) << "the parts' colour differs from the one-file export";
  EXPECT_TRUE(gathered.ct == whole_ct) << "the parts' CT differs from the one-file export";
  EXPECT_TRUE(gathered.labels == whole_labels)
      << "the parts' labels differ from the one-file export";
  ASSERT_TRUE(merged);
  EXPECT_TRUE(active_voxels(*merged) == whole_rgb);

  const auto report = nlohmann::json::parse(read_file(config.work_dir + "/vdb/report.json"));
  EXPECT_EQ(report["layout"], "parts");
  EXPECT_EQ(report["level"], 0);
  EXPECT_NE(report["layout_reason"].get<std::string>().find("over vdb.max_memory_mb"),
            std::string::npos)
      << report["layout_reason"];
  EXPECT_EQ(report["parts"].size(), parts.size());
  EXPECT_EQ(run_vdb_stage(config, quiet_stage()).processed, 0) << "not up to date on a rerun";

  // Under the default budget the same output is one file; the parts and their index go.
  const Config back = config_with(nlohmann::json::object(), "parts.vdb");
  EXPECT_EQ(run_vdb_stage(back, quiet_stage()).output, back.vdb_output);
  EXPECT_TRUE(fs::exists(back.vdb_output));
  EXPECT_FALSE(fs::exists(index));
  for (const auto& p : parts)
    EXPECT_FALSE(fs::exists(fs::path(index).parent_path() / p["file"].get<std::string>()));
}

// The cluster path (shards, --slices A:B) over the budget exports the asked level as the same
// parts as one process: every shard plans the same parts and writes those that start in its
// slices' level z range; the last shard to finish writes the index, the same text as the one
// process's (same files, sizes, leaves, reason). Each part holds the one process's voxels; each
// shard's report says the level, the layout and why.
TEST_F(VdbLevels, ShardsWriteTheSamePartsAsOneProcess) {
  const Config config = config_with(
      {{"max_memory_mb",
        third_of_level_zero_mb(format::Reader::open(load_config(*dir_ / "config.json").output))}},
      "sharded.vdb");
  const std::string index = vdb_parts_index_path(config);
  const fs::path out = fs::path(index).parent_path();
  // The part files of this export in the output folder, by name.
  auto part_files = [&] {
    std::vector<std::string> names;
    for (const auto& f : fs::directory_iterator(out))
      if (f.path().filename().string().rfind("sharded.slices-", 0) == 0)
        names.push_back(f.path().filename().string());
    std::sort(names.begin(), names.end());
    return names;
  };
  struct Voxels {
    std::map<std::array<int, 3>, openvdb::Vec3s> rgb;
    std::map<std::array<int, 3>, float> ct;
    std::map<std::array<int, 3>, int> labels;
    bool operator==(const Voxels& o) const {
      return rgb == o.rgb && ct == o.ct && labels == o.labels;
    }
  };
  openvdb::initialize();
  auto read_parts = [&] {
    std::map<std::string, Voxels> parts;
    for (const auto& name : part_files()) {
      const std::string path = out / name;
      parts[name] = {active_voxels(*read_grid<openvdb::Vec3SGrid>(path, "rgb")),
                     active_voxels(*read_grid<openvdb::FloatGrid>(path, "ct")),
                     active_voxels(*read_grid<openvdb::Int32Grid>(path, "labels"))};
    }
    return parts;
  };

  // One process.
  ASSERT_EQ(run_vdb_stage(config, quiet_stage()).output, index);
  const std::string one_index = read_file(index);
  const auto one_parts = read_parts();
  ASSERT_GE(one_parts.size(), 3u);
  for (const auto& [name, voxels] : one_parts)
    fs::remove(out / name);
  fs::remove(index);

  // Three shards whose bounds are not the parts' (one may own no part).
  const std::vector<std::pair<int, int>> shards = {{0, 10}, {10, 41}, {41, 64}};
  for (std::size_t s = 0; s < shards.size(); ++s) {
    const auto [a, b] = shards[s];
    SCOPED_TRACE(cat("shard ", a, ":", b));
    StageOptions so = quiet_stage();
    so.slices = cat(a, ":", b);
    const StageResult r = run_vdb_stage(config, so);
    EXPECT_EQ(r.processed, 1);
    const bool last = s + 1 == shards.size();
    EXPECT_EQ(fs::exists(index), last) << "the index before every part was written";
    if (last) {
      EXPECT_EQ(r.output, index);
    }
    const auto report = nlohmann::json::parse(
        read_file(cat(config.work_dir, "/vdb-parts/report-", a, "-", b, ".json")));
    EXPECT_EQ(report["level"], 0);
    EXPECT_EQ(report["layout"], "parts");
    EXPECT_NE(report["layout_reason"].get<std::string>().find("level 0 needs"), std::string::npos)
        << report["layout_reason"];
    EXPECT_NE(report["layout_reason"].get<std::string>().find("over vdb.max_memory_mb"),
              std::string::npos)
        << report["layout_reason"];
    EXPECT_EQ(report["parts_planned"], one_parts.size());
    EXPECT_EQ(report["index_complete"], last);
    std::printf("shard %d:%d wrote %zu of %zu parts\n", a, b, report["parts"].size(),
                one_parts.size());
    EXPECT_EQ(run_vdb_stage(config, so).processed, 0) << "not up to date on a rerun";
  }
  EXPECT_EQ(read_file(index), one_index) << "the shards' index differs from one process's";
  const auto sharded_parts = read_parts();
  ASSERT_EQ(sharded_parts.size(), one_parts.size());
  for (const auto& [name, voxels] : one_parts) {
    ASSERT_TRUE(sharded_parts.count(name)) << name << ": not written by the shards";
    EXPECT_TRUE(sharded_parts.at(name) == voxels) << name << ": voxels differ";
  }
  EXPECT_FALSE(fs::exists(config.vdb_output));
  // The index missing, a shard found up to date writes it again from the records.
  fs::remove(index);
  StageOptions so = quiet_stage();
  so.slices = "0:10";
  EXPECT_EQ(run_vdb_stage(config, so).output, index);
  EXPECT_EQ(read_file(index), one_index);
}

// vdb.level over the budget: a ConfigError naming the key, the level, the estimate and the
// budget; nothing is written. A level the file does not have: a ConfigError too.
TEST_F(VdbLevels, ExplicitLevelOverBudgetIsAConfigError) {
  Config config = config_with({{"level", 0}, {"max_memory_mb", 100}}, "over.vdb");
  try {
    run_vdb_stage(config, quiet_stage());
    FAIL() << "no error";
  } catch (const ConfigError& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("vdb.level: level 0 ("), std::string::npos) << m;
    EXPECT_NE(m.find("of budget 100.0 MB"), std::string::npos) << m;
    EXPECT_NE(m.find("does not fit vdb.max_memory_mb"), std::string::npos) << m;
  }
  EXPECT_FALSE(std::filesystem::exists(config.vdb_output));
  Config deep = config_with({{"level", 15}}, "deep.vdb");
  EXPECT_THROW(run_vdb_stage(deep, quiet_stage()), ConfigError);
  // The same through the command line: the config error's exit code, the message on stderr.
  auto r = test::run_command_split(test::bin("vispack-vdb") + " --config " + config.path);
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("does not fit vdb.max_memory_mb"), std::string::npos) << r.err;
}

TEST(VdbConfig, LevelAndBudgetKeys) {
  test::TempDir dir;
  PhantomOptions po;
  po.preset = "tiny";
  po.seed = 1;
  po.quiet = true;
  make_phantom(dir.path(), po);
  auto load_with = [&](const nlohmann::json& vdb) {
    auto j = nlohmann::json::parse(read_file(dir / "config.json"));
    j["vdb"] = vdb;
    write_file_atomic(dir / "c.json", j.dump());
    return load_config(dir / "c.json");
  };
  Config c = load_with(nlohmann::json::object());
  EXPECT_FALSE(c.vdb.level.has_value());
  EXPECT_EQ(c.vdb.max_memory_mb, 1024);
  EXPECT_EQ(c.vdb.layout, VdbLayout::kAuto);
  c = load_with({{"level", "auto"}, {"max_memory_mb", 500}, {"layout", "file"}});
  EXPECT_FALSE(c.vdb.level.has_value());
  EXPECT_EQ(c.vdb.max_memory_mb, 500);
  EXPECT_EQ(c.vdb.layout, VdbLayout::kFile);
  EXPECT_EQ(load_with({{"layout", "auto"}}).vdb.layout, VdbLayout::kAuto);
  EXPECT_THROW(load_with({{"layout", "parts"}}), ConfigError);
  EXPECT_EQ(load_with({{"level", 2}}).vdb.level, 2);
  EXPECT_THROW(load_with({{"level", "fine"}}), ConfigError);
  EXPECT_THROW(load_with({{"level", -1}}), ConfigError);
  EXPECT_THROW(load_with({{"max_memory_mb", 0}}), ConfigError);
}

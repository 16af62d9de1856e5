#include "vispack/pipeline/vdb/vdb.h"

#include <sys/resource.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>

#include <openvdb/openvdb.h>
#include <tbb/global_control.h>
#include <tbb/task_arena.h>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/format/reader.h"
#include "vispack/pipeline/core/version.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/vdb/vdb_level.h"
#include "vispack/pipeline/vdb/vdb_write.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

namespace {

// One brick of one channel as edge^3 voxels: decoded into `buffer`, or the uniform value
// repeated. Returns buffer.data().
const std::uint8_t* brick_voxels(const format::Reader& reader, const format::BrickInfo& b,
                                 std::vector<std::uint8_t>& buffer) {
  const std::size_t bytes = reader.brick_bytes(b.channel);
  buffer.resize(bytes);
  if (b.codec == format::Codec::kUniform) {
    const std::size_t vb =
        format::channel_type_bytes(reader.channels()[std::size_t(b.channel)].type);
    for (std::size_t i = 0; i < bytes; i += vb)
      std::memcpy(buffer.data() + i, b.uniform.data(), vb);
  } else {
    reader.decode_brick(b, buffer.data(), buffer.size());
  }
  return buffer.data();
}

double peak_rss_mb() {
  struct rusage usage {};
  getrusage(RUSAGE_SELF, &usage);
  return double(usage.ru_maxrss) / 1024.0;  // ru_maxrss is in KiB on Linux
}

nlohmann::json estimate_json(const VdbLevelEstimate& e) {
  return {{"level", e.level},
          {"dims", e.dims},
          {"active_voxels", e.active_voxels},
          {"leaves", e.leaves},
          {"mapped_mb", double(e.mapped_bytes) / (1024.0 * 1024.0)},
          {"scanned_mb", double(e.scanned_bytes) / (1024.0 * 1024.0)},
          {"estimated_mb", e.bytes / (1024.0 * 1024.0)},
          {"exact", e.exact}};
}

}  // namespace

std::string vdb_part_path(const Config& config, int first, int last) {
  const fs::path whole(config.vdb_output);
  char range[64];
  std::snprintf(range, sizeof range, ".slices-%04d-%04d", first, last);
  return (whole.parent_path() / (whole.stem().string() + range + ".vdb")).string();
}

namespace {

// The export itself: run_vdb_stage runs it inside its TBB arena.
StageResult export_vdb(const Config& config, const StageOptions& options) {
  if (!config.vdb.enabled || config.vdb_output.empty())
    throw ConfigError(cat(config.path, ": vdb.enabled is false: no OpenVDB export configured"));
  const int stack = int(stack_slices(config).size());
  SliceRange part{0, stack};
  if (!options.slices.empty()) part = parse_slice_range(options.slices, stack);
  const bool sharded = part.first != 0 || part.last != stack;
  if (!fs::exists(config.output))
    throw InputError(cat(config.output,
                         ": packed file missing: vispack-vdb exports the packed "
                         "file's pyramid (run vispack-pack first)"));

  // Unsharded: one unit (the file) in work/vdb. A shard: its part file is unit `part.first` of
  // work/vdb-parts (a shard's manifest records only its own part).
  const std::string output =
      sharded ? vdb_part_path(config, part.first, part.last) : config.vdb_output;
  Fingerprint fp;
  fp.file(config.output).text(output);
  if (sharded) fp.text(cat(part.first, ":", part.last));
  StageOptions unit = options;
  if (!sharded) unit.slices.clear();
  StageRun run(config, sharded ? "vdb-parts" : "vdb", sharded ? stack : 1, unit, {"vdb"});
  const int unit_index = sharded ? part.first : 0;
  run.remove_stale_temporaries_of(output);
  const std::string input = fp.str();
  if (run.up_to_date(unit_index, input, {output})) {
    run.skip(unit_index);
    return run.finish(output);
  }

  const format::Reader reader = format::Reader::open(config.output);
  const VdbLevelChoice choice = choose_vdb_level(config, reader, run.threads());
  const int level = choice.level;
  const format::LevelInfo& info = reader.level(level);
  const std::string chosen = describe_vdb_choice(choice);
  if (!options.quiet)
    std::printf(
        "vdb: exporting %s (%s)%s\n", chosen.c_str(),
        choice.automatic ? "the finest level within vdb.max_memory_mb" : "vdb.level",
        sharded ? cat(", slices ", part.first, ":", part.last, " to ", output).c_str() : "");
  std::fflush(stdout);

  const int rgba = reader.channel_index("rgba");
  const std::optional<int> ct_channel = reader.find_channel("ct");
  const std::optional<int> label_channel = reader.find_channel("labels");
  const bool labels16 = label_channel && reader.channels()[std::size_t(*label_channel)].type ==
                                             format::ChannelType::kUint16;

  openvdb::initialize();
  // Index (i, j, k) of the level has its centre at origin_mm + (i, j, k) * spacing_mm.
  openvdb::math::Mat4d scale = openvdb::math::Mat4d::identity();
  scale.setToScale(openvdb::Vec3d(info.spacing_mm[0], info.spacing_mm[1], info.spacing_mm[2]));
  auto xform = openvdb::math::Transform::createLinearTransform(scale);
  xform->postTranslate(openvdb::Vec3d(info.origin_mm[0], info.origin_mm[1], info.origin_mm[2]));

  // The bricks of this part that hold body (packed alpha > 0 somewhere), in index order; a voxel
  // is active where the packed alpha (body coverage) is > 0: at level 0 of an undownsampled file
  // exactly the body mask.
  const std::int64_t edge = reader.brick_edge();
  const auto& grid = info.bricks;
  // The level's z range of this part: ceil(A * D / S) .. ceil(B * D / S) (the whole level when
  // not sharded); consecutive shards meet exactly, so their parts tile the level.
  const std::int64_t depth = info.dims[2];
  const auto level_z = [&](int s) { return (std::int64_t(s) * depth + stack - 1) / stack; };
  const std::int64_t z_first = sharded ? level_z(part.first) : 0;
  const std::int64_t z_last = sharded ? level_z(part.last) : depth;
  const std::int64_t bz_first = z_first / edge, bz_last = (z_last + edge - 1) / edge;
  std::vector<std::array<std::int64_t, 3>> body_bricks;
  for (std::int64_t bz = bz_first; bz < bz_last; ++bz)
    for (std::int64_t by = 0; by < grid[1]; ++by)
      for (std::int64_t bx = 0; bx < grid[0]; ++bx)
        if (reader.brick(rgba, level, bx, by, bz).max[3] != 0) body_bricks.push_back({bx, by, bz});

  // The grids are built on run.threads() threads, each from a contiguous run of those bricks
  // into grids of its own, then merged in order (OpenVDB trees take values from one thread). The
  // runs' leaves (8^3 voxels) are disjoint when the brick edge is a multiple of 8, so the merge
  // only moves nodes and the trees equal a one-thread build; other edges build on one thread.
  struct Part {
    openvdb::FloatGrid::Ptr ct = openvdb::FloatGrid::create(-1024.0f);
    openvdb::Int32Grid::Ptr labels = openvdb::Int32Grid::create(0);
    openvdb::Vec3SGrid::Ptr rgb = openvdb::Vec3SGrid::create(openvdb::Vec3s(0, 0, 0));
    std::uint64_t active = 0;
  };
  // With a brick edge that is a multiple of the leaf edge (8), each brick is whole leaves: they
  // are filled directly and added to the trees (a leaf per 8^3 voxels holding body, inactive
  // voxels at the background, as voxel-by-voxel accessor writes leave them, without an accessor
  // lookup per voxel); edge 4 takes the accessor.
  constexpr int kLeaf = 8;
  using CtLeaf = openvdb::FloatTree::LeafNodeType;
  using LabelLeaf = openvdb::Int32Tree::LeafNodeType;
  using RgbLeaf = openvdb::Vec3STree::LeafNodeType;
  static_assert(CtLeaf::DIM == kLeaf && LabelLeaf::DIM == kLeaf && RgbLeaf::DIM == kLeaf);
  const bool by_leaves = edge % kLeaf == 0;
  const int workers =
      int(std::clamp<std::int64_t>(by_leaves ? run.threads() : 1, 1,
                                   std::max<std::int64_t>(1, std::int64_t(body_bricks.size()))));
  std::vector<Part> parts(static_cast<std::size_t>(workers));
  parallel_for(workers, workers, [&](std::int64_t w) {
    Part& out = parts[std::size_t(w)];
    auto ct_acc = out.ct->getAccessor();
    auto label_acc = out.labels->getAccessor();
    auto rgb_acc = out.rgb->getAccessor();
    std::vector<std::uint8_t> rgba_buf, ct_buf, label_buf;
    const std::size_t n = body_bricks.size();
    for (std::size_t i = n * std::size_t(w) / std::size_t(workers);
         i < n * std::size_t(w + 1) / std::size_t(workers); ++i) {
      const auto [bx, by, bz] = body_bricks[i];
      const std::uint8_t* c = brick_voxels(reader, reader.brick(rgba, level, bx, by, bz), rgba_buf);
      const std::uint8_t* h =
          ct_channel ? brick_voxels(reader, reader.brick(*ct_channel, level, bx, by, bz), ct_buf)
                     : nullptr;
      const std::uint8_t* l =
          label_channel
              ? brick_voxels(reader, reader.brick(*label_channel, level, bx, by, bz), label_buf)
              : nullptr;
      const std::int64_t nx = std::min(edge, info.dims[0] - bx * edge);
      const std::int64_t ny = std::min(edge, info.dims[1] - by * edge);
      const std::int64_t z_begin = std::max<std::int64_t>(0, z_first - bz * edge);
      const std::int64_t nz = std::min(edge, z_last - bz * edge);
      const auto hu_at = [&](std::size_t v) {
        std::int16_t hu;
        std::memcpy(&hu, h + 2 * v, 2);
        return float(hu);
      };
      const auto id_at = [&](std::size_t v) {
        std::uint16_t id = l[v];
        if (labels16) std::memcpy(&id, l + 2 * v, 2);
        return int(id);
      };
      if (!by_leaves) {
        for (std::int64_t z = z_begin; z < nz; ++z)
          for (std::int64_t y = 0; y < ny; ++y)
            for (std::int64_t x = 0; x < nx; ++x) {
              const std::size_t v = std::size_t((z * edge + y) * edge + x);
              const std::uint8_t* px = c + 4 * v;
              if (px[3] == 0) continue;
              const openvdb::Coord ijk(int(bx * edge + x), int(by * edge + y), int(bz * edge + z));
              rgb_acc.setValue(ijk, openvdb::Vec3s(px[0] / 255.0f, px[1] / 255.0f, px[2] / 255.0f));
              if (h) ct_acc.setValue(ijk, hu_at(v));
              if (l) label_acc.setValue(ijk, id_at(v));
              ++out.active;
            }
        continue;
      }
      for (std::int64_t lz = z_begin / kLeaf * kLeaf; lz < nz; lz += kLeaf)
        for (std::int64_t ly = 0; ly < ny; ly += kLeaf)
          for (std::int64_t lx = 0; lx < nx; lx += kLeaf) {
            const openvdb::Coord origin(int(bx * edge + lx), int(by * edge + ly),
                                        int(bz * edge + lz));
            std::unique_ptr<RgbLeaf> rgb_leaf;
            std::unique_ptr<CtLeaf> ct_leaf;
            std::unique_ptr<LabelLeaf> label_leaf;
            for (std::int64_t z = std::max(lz, z_begin); z < std::min(lz + kLeaf, nz); ++z)
              for (std::int64_t y = ly; y < std::min(ly + kLeaf, ny); ++y)
                for (std::int64_t x = lx; x < std::min(lx + kLeaf, nx); ++x) {
                  const std::size_t v = std::size_t((z * edge + y) * edge + x);
                  const std::uint8_t* px = c + 4 * v;
                  if (px[3] == 0) continue;
                  if (!rgb_leaf) {
                    rgb_leaf = std::make_unique<RgbLeaf>(origin, out.rgb->background(), false);
                    if (h) ct_leaf = std::make_unique<CtLeaf>(origin, out.ct->background(), false);
                    if (l)
                      label_leaf =
                          std::make_unique<LabelLeaf>(origin, out.labels->background(), false);
                  }
                  // A leaf's offset: x slowest, z fastest (LeafNode::coordToOffset).
                  const openvdb::Index offset =
                      openvdb::Index(((x - lx) << 6) | ((y - ly) << 3) | (z - lz));
                  rgb_leaf->setValueOn(
                      offset, openvdb::Vec3s(px[0] / 255.0f, px[1] / 255.0f, px[2] / 255.0f));
                  if (ct_leaf) ct_leaf->setValueOn(offset, hu_at(v));
                  if (label_leaf) label_leaf->setValueOn(offset, id_at(v));
                  ++out.active;
                }
            if (!rgb_leaf) continue;
            out.rgb->tree().addLeaf(rgb_leaf.release());
            if (ct_leaf) out.ct->tree().addLeaf(ct_leaf.release());
            if (label_leaf) out.labels->tree().addLeaf(label_leaf.release());
          }
    }
  });
  openvdb::FloatGrid::Ptr ct_grid = parts[0].ct;
  openvdb::Int32Grid::Ptr label_grid = parts[0].labels;
  openvdb::Vec3SGrid::Ptr rgb_grid = parts[0].rgb;
  std::uint64_t active = parts[0].active;
  for (std::size_t w = 1; w < parts.size(); ++w) {
    ct_grid->tree().merge(parts[w].ct->tree(), openvdb::MERGE_ACTIVE_STATES);
    label_grid->tree().merge(parts[w].labels->tree(), openvdb::MERGE_ACTIVE_STATES);
    rgb_grid->tree().merge(parts[w].rgb->tree(), openvdb::MERGE_ACTIVE_STATES);
    active += parts[w].active;
  }
  parts.resize(1);
  ct_grid->setTransform(xform);
  label_grid->setTransform(xform->copy());
  rgb_grid->setTransform(xform->copy());

  // Said in the file (per grid and for the file), the report and the stdout line above.
  openvdb::MetaMap meta;
  meta.insertMeta("vispack_version", openvdb::StringMetadata(version_string()));
  meta.insertMeta("vispack_level", openvdb::Int32Metadata(level));
  meta.insertMeta("vispack_level_choice",
                  openvdb::StringMetadata(choice.automatic ? "auto" : "vdb.level"));
  meta.insertMeta("vispack_voxel_size_mm",
                  openvdb::Vec3DMetadata(
                      openvdb::Vec3d(info.spacing_mm[0], info.spacing_mm[1], info.spacing_mm[2])));
  meta.insertMeta("vispack_origin_mm",
                  openvdb::Vec3DMetadata(
                      openvdb::Vec3d(info.origin_mm[0], info.origin_mm[1], info.origin_mm[2])));
  meta.insertMeta("vispack_source", openvdb::StringMetadata(fs::path(config.output).filename()));
  if (sharded) {
    meta.insertMeta("vispack_part_slices",
                    openvdb::StringMetadata(cat(part.first, ":", part.last)));
    meta.insertMeta("vispack_part_z", openvdb::StringMetadata(cat(z_first, ":", z_last)));
  }
  openvdb::GridPtrVec grids;
  auto name_grid = [&](openvdb::GridBase::Ptr g, const char* name, const char* units) {
    g->setName(name);
    for (auto it = meta.beginMeta(); it != meta.endMeta(); ++it)
      g->insertMeta(it->first, *it->second);
    g->insertMeta("units", openvdb::StringMetadata(units));
    grids.push_back(g);
  };
  if (ct_channel) name_grid(ct_grid, "ct", "HU");
  if (label_channel) name_grid(label_grid, "labels", "id");
  name_grid(rgb_grid, "rgb", "rgb01");
  const std::uint64_t leaves = rgb_grid->tree().leafCount();

  make_directories(fs::path(output).parent_path().string());
  // Written to a temporary name and renamed into place (removed on any failure); the write
  // system calls overlap OpenVDB's serialisation when a second thread is allowed.
  write_vdb_grids(output, openvdb::GridCPtrVec(grids.begin(), grids.end()), meta,
                  run.threads() > 1);
  run.done(unit_index, input, {output}, reader.file_size());
  run.set_report("output", output);
  run.set_report("output_bytes", std::uint64_t(fs::file_size(output)));
  if (sharded) {
    run.set_report("part_slices", {part.first, part.last});
    run.set_report("part_z", {z_first, z_last});
  }
  nlohmann::json names = nlohmann::json::array();
  for (const auto& g : grids)
    names.push_back(g->getName());
  run.set_report("grids", names);
  run.set_report("level", level);
  run.set_report("level_choice", choice.automatic ? "auto" : "vdb.level");
  run.set_report("voxel_size_mm", info.spacing_mm);
  run.set_report("origin_mm", info.origin_mm);
  run.set_report("max_memory_mb", config.vdb.max_memory_mb);
  nlohmann::json estimates = nlohmann::json::array();
  for (const auto& e : choice.estimates)
    estimates.push_back(estimate_json(e));
  run.set_report("estimates", estimates);
  run.set_report("peak_rss_mb", peak_rss_mb());
  run.set_quality("active_voxels", active);
  run.set_quality("leaves", leaves);
  return run.finish(output);
}

}  // namespace

StageResult run_vdb_stage(const Config& config, const StageOptions& options) {
  // OpenVDB's own parallel loops (TBB: the delayed-load metadata it computes while writing)
  // stay within --threads too: a task given one core uses one. The export runs in an arena of
  // that many threads, so its loops ask TBB for no more workers than that (with one thread, for
  // none: no worker wakes, not even after the stage, when a limit alone would lift and let a
  // worker visit the loops' old arena); the global limit bounds loops reached from any other
  // thread (the writer's second thread).
  const int threads = resolve_threads(options.threads);
  const tbb::global_control tbb_threads(tbb::global_control::max_allowed_parallelism,
                                        std::size_t(threads));
  tbb::task_arena arena(threads);
  return arena.execute([&] { return export_vdb(config, options); });
}

}  // namespace vispack::pipeline

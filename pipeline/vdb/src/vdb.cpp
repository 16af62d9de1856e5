#include "vispack/pipeline/vdb/vdb.h"

#include <malloc.h>
#include <sys/resource.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <system_error>
#include <vector>

#include <openvdb/openvdb.h>
#include <tbb/global_control.h>
#include <tbb/task_arena.h>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/format/reader.h"
#include "vispack/pipeline/core/slice_z.h"
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

std::string vdb_parts_index_path(const Config& config) {
  const fs::path whole(config.vdb_output);
  return (whole.parent_path() / (whole.stem().string() + ".parts.json")).string();
}

namespace {

// The part of the chosen level one export writes: level z in [z_first, z_last) (the whole level
// unless sharded) and the bricks there that hold body (packed alpha > 0 somewhere), in index
// order.
struct LevelPart {
  std::int64_t z_first = 0, z_last = 0;
  std::vector<std::array<std::int64_t, 3>> body_bricks;
};

// The level's z range [z_first, z_last) and its body bricks.
LevelPart level_part_z(const format::Reader& reader, int rgba, int level, std::int64_t z_first,
                       std::int64_t z_last) {
  const auto& grid = reader.level(level).bricks;
  const std::int64_t edge = reader.brick_edge();
  LevelPart out;
  out.z_first = z_first;
  out.z_last = z_last;
  const std::int64_t bz_first = z_first / edge, bz_last = (z_last + edge - 1) / edge;
  for (std::int64_t bz = bz_first; bz < bz_last; ++bz)
    for (std::int64_t by = 0; by < grid[1]; ++by)
      for (std::int64_t bx = 0; bx < grid[0]; ++bx)
        if (reader.brick(rgba, level, bx, by, bz).max[3] != 0)
          out.body_bricks.push_back({bx, by, bz});
  return out;
}

// The level z where stack slice s begins, for a level of `depth` slices: ceil(s * depth /
// stack). Consecutive shards [A, B) [B, C) meet exactly, so their parts tile the level.
std::int64_t level_z_of_slice(int s, std::int64_t depth, int stack) {
  return (std::int64_t(s) * depth + stack - 1) / stack;
}

// The first stack slice whose level z is `z` (the inverse of level_z_of_slice for a level no
// deeper than the stack): the slices a part of level z range covers, for its name.
int slice_of_level_z(std::int64_t z, std::int64_t depth, int stack) {
  if (z <= 0) return 0;
  if (z >= depth) return stack;
  const int s = int((z - 1) * stack / depth + 1);
  if (level_z_of_slice(s, depth, stack) != z)
    throw std::logic_error(cat("vdb: level z ", z, " of ", depth, " starts no slice of ", stack));
  return s;
}

LevelPart level_part(const format::Reader& reader, int rgba, int level, SliceRange part,
                     int stack) {
  const std::int64_t depth = reader.level(level).dims[2];
  return level_part_z(reader, rgba, level, level_z_of_slice(part.first, depth, stack),
                      level_z_of_slice(part.last, depth, stack));
}

// The channels of the packed file the export reads.
struct ExportChannels {
  int rgba = 0;
  std::optional<int> ct, labels;
  bool labels16 = false;
};

ExportChannels export_channels(const format::Reader& reader) {
  ExportChannels c;
  c.rgba = reader.channel_index("rgba");
  c.ct = reader.find_channel("ct");
  c.labels = reader.find_channel("labels");
  c.labels16 =
      c.labels && reader.channels()[std::size_t(*c.labels)].type == format::ChannelType::kUint16;
  return c;
}

// The three grids of one builder thread (or, merged, of the export).
struct ExportGrids {
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

// One decoded brick of each channel (ct and labels null when the file has none) and the
// brick's voxel box inside the part: x < nx, y < ny, z in [z_begin, nz), brick-local.
struct BrickVoxels {
  const std::uint8_t* rgba = nullptr;
  const std::uint8_t* ct = nullptr;
  const std::uint8_t* labels = nullptr;
  bool labels16 = false;
  std::int64_t edge = 0, nx = 0, ny = 0, z_begin = 0, nz = 0;
  std::size_t offset(std::int64_t x, std::int64_t y, std::int64_t z) const {
    return std::size_t((z * edge + y) * edge + x);
  }
  openvdb::Vec3s rgb_at(std::size_t v) const {
    const std::uint8_t* px = rgba + 4 * v;
    return {px[0] / 255.0f, px[1] / 255.0f, px[2] / 255.0f};
  }
  bool body_at(std::size_t v) const { return rgba[4 * v + 3] != 0; }
  float hu_at(std::size_t v) const {
    std::int16_t hu;
    std::memcpy(&hu, ct + 2 * v, 2);
    return float(hu);
  }
  int id_at(std::size_t v) const {
    std::uint16_t id = labels[v];
    if (labels16) std::memcpy(&id, labels + 2 * v, 2);
    return int(id);
  }
};

// The brick's body voxels written one by one through accessors (any brick edge).
void add_brick_by_voxels(const BrickVoxels& b, const openvdb::Coord& brick_origin,
                         ExportGrids& out) {
  auto ct_acc = out.ct->getAccessor();
  auto label_acc = out.labels->getAccessor();
  auto rgb_acc = out.rgb->getAccessor();
  for (std::int64_t z = b.z_begin; z < b.nz; ++z)
    for (std::int64_t y = 0; y < b.ny; ++y)
      for (std::int64_t x = 0; x < b.nx; ++x) {
        const std::size_t v = b.offset(x, y, z);
        if (!b.body_at(v)) continue;
        const openvdb::Coord ijk = brick_origin.offsetBy(int(x), int(y), int(z));
        rgb_acc.setValue(ijk, b.rgb_at(v));
        if (b.ct) ct_acc.setValue(ijk, b.hu_at(v));
        if (b.labels) label_acc.setValue(ijk, b.id_at(v));
        ++out.active;
      }
}

// The brick's body voxels as whole leaves added to the trees (brick edge a multiple of 8).
void add_brick_by_leaves(const BrickVoxels& b, const openvdb::Coord& brick_origin,
                         ExportGrids& out) {
  for (std::int64_t lz = b.z_begin / kLeaf * kLeaf; lz < b.nz; lz += kLeaf)
    for (std::int64_t ly = 0; ly < b.ny; ly += kLeaf)
      for (std::int64_t lx = 0; lx < b.nx; lx += kLeaf) {
        const openvdb::Coord origin = brick_origin.offsetBy(int(lx), int(ly), int(lz));
        std::unique_ptr<RgbLeaf> rgb_leaf;
        std::unique_ptr<CtLeaf> ct_leaf;
        std::unique_ptr<LabelLeaf> label_leaf;
        for (std::int64_t z = std::max(lz, b.z_begin); z < std::min(lz + kLeaf, b.nz); ++z)
          for (std::int64_t y = ly; y < std::min(ly + kLeaf, b.ny); ++y)
            for (std::int64_t x = lx; x < std::min(lx + kLeaf, b.nx); ++x) {
              const std::size_t v = b.offset(x, y, z);
              if (!b.body_at(v)) continue;
              if (!rgb_leaf) {
                rgb_leaf = std::make_unique<RgbLeaf>(origin, out.rgb->background(), false);
                if (b.ct) ct_leaf = std::make_unique<CtLeaf>(origin, out.ct->background(), false);
                if (b.labels)
                  label_leaf = std::make_unique<LabelLeaf>(origin, out.labels->background(), false);
              }
              // A leaf's offset: x slowest, z fastest (LeafNode::coordToOffset).
              const openvdb::Index offset =
                  openvdb::Index(((x - lx) << 6) | ((y - ly) << 3) | (z - lz));
              rgb_leaf->setValueOn(offset, b.rgb_at(v));
              if (ct_leaf) ct_leaf->setValueOn(offset, b.hu_at(v));
              if (label_leaf) label_leaf->setValueOn(offset, b.id_at(v));
              ++out.active;
            }
        if (!rgb_leaf) continue;
        out.rgb->tree().addLeaf(rgb_leaf.release());
        if (ct_leaf) out.ct->tree().addLeaf(ct_leaf.release());
        if (label_leaf) out.labels->tree().addLeaf(label_leaf.release());
      }
}

// The grids of the part's body bricks, built on up to `threads` threads, each from a contiguous
// run of those bricks into grids of its own, then merged in order (OpenVDB trees take values
// from one thread). The runs' leaves (8^3 voxels) are disjoint when the brick edge is a
// multiple of 8, so the merge only moves nodes and the trees equal a one-thread build; other
// edges build on one thread.
ExportGrids build_grids(const format::Reader& reader, int level, const ExportChannels& channels,
                        const LevelPart& part, int threads) {
  const format::LevelInfo& info = reader.level(level);
  const std::int64_t edge = reader.brick_edge();
  const bool by_leaves = edge % kLeaf == 0;
  const auto& bricks = part.body_bricks;
  const int workers = int(std::clamp<std::int64_t>(
      by_leaves ? threads : 1, 1, std::max<std::int64_t>(1, std::int64_t(bricks.size()))));
  std::vector<ExportGrids> grids(static_cast<std::size_t>(workers));
  parallel_for(workers, workers, [&](std::int64_t w) {
    std::vector<std::uint8_t> rgba_buf, ct_buf, label_buf;
    const std::size_t n = bricks.size();
    for (std::size_t i = n * std::size_t(w) / std::size_t(workers);
         i < n * std::size_t(w + 1) / std::size_t(workers); ++i) {
      const auto [bx, by, bz] = bricks[i];
      BrickVoxels b;
      b.rgba = brick_voxels(reader, reader.brick(channels.rgba, level, bx, by, bz), rgba_buf);
      if (channels.ct)
        b.ct = brick_voxels(reader, reader.brick(*channels.ct, level, bx, by, bz), ct_buf);
      if (channels.labels)
        b.labels =
            brick_voxels(reader, reader.brick(*channels.labels, level, bx, by, bz), label_buf);
      // Decoded: the file's pages need not stay resident (the export's memory is its grids).
      reader.release_payload_pages(reader.brick(channels.rgba, level, bx, by, bz));
      if (channels.ct) reader.release_payload_pages(reader.brick(*channels.ct, level, bx, by, bz));
      if (channels.labels)
        reader.release_payload_pages(reader.brick(*channels.labels, level, bx, by, bz));
      b.labels16 = channels.labels16;
      b.edge = edge;
      b.nx = std::min(edge, info.dims[0] - bx * edge);
      b.ny = std::min(edge, info.dims[1] - by * edge);
      b.z_begin = std::max<std::int64_t>(0, part.z_first - bz * edge);
      b.nz = std::min(edge, part.z_last - bz * edge);
      const openvdb::Coord origin(int(bx * edge), int(by * edge), int(bz * edge));
      if (by_leaves)
        add_brick_by_leaves(b, origin, grids[std::size_t(w)]);
      else
        add_brick_by_voxels(b, origin, grids[std::size_t(w)]);
    }
  });
  ExportGrids out = grids[0];
  for (std::size_t w = 1; w < grids.size(); ++w) {
    out.ct->tree().merge(grids[w].ct->tree(), openvdb::MERGE_ACTIVE_STATES);
    out.labels->tree().merge(grids[w].labels->tree(), openvdb::MERGE_ACTIVE_STATES);
    out.rgb->tree().merge(grids[w].rgb->tree(), openvdb::MERGE_ACTIVE_STATES);
    out.active += grids[w].active;
  }
  // Index (i, j, k) of the level has its centre at origin_mm + (i, j, k) * spacing_mm.
  openvdb::math::Mat4d scale = openvdb::math::Mat4d::identity();
  scale.setToScale(openvdb::Vec3d(info.spacing_mm[0], info.spacing_mm[1], info.spacing_mm[2]));
  auto xform = openvdb::math::Transform::createLinearTransform(scale);
  xform->postTranslate(openvdb::Vec3d(info.origin_mm[0], info.origin_mm[1], info.origin_mm[2]));
  out.ct->setTransform(xform);
  out.labels->setTransform(xform->copy());
  out.rgb->setTransform(xform->copy());
  return out;
}

// What the file says of itself (per grid and for the file): version, level and how it was
// chosen, voxel size and origin in mm, the source, and a shard's slices and level z range.
openvdb::MetaMap export_metadata(const Config& config, const format::LevelInfo& info,
                                 const VdbLevelChoice& choice, bool sharded, SliceRange slices,
                                 const LevelPart& part) {
  openvdb::MetaMap meta;
  meta.insertMeta("vispack_version", openvdb::StringMetadata(version_string()));
  meta.insertMeta("vispack_level", openvdb::Int32Metadata(choice.level));
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
                    openvdb::StringMetadata(cat(slices.first, ":", slices.last)));
    meta.insertMeta("vispack_part_z", openvdb::StringMetadata(cat(part.z_first, ":", part.z_last)));
  }
  return meta;
}

// The grids the file holds, named, each carrying `meta` and its units: ct (HU) and labels (id)
// when the packed file has them, rgb (0..1) always.
openvdb::GridPtrVec named_grids(const ExportGrids& grids, const ExportChannels& channels,
                                const openvdb::MetaMap& meta) {
  openvdb::GridPtrVec out;
  auto name_grid = [&](openvdb::GridBase::Ptr g, const char* name, const char* units) {
    g->setName(name);
    for (auto it = meta.beginMeta(); it != meta.endMeta(); ++it)
      g->insertMeta(it->first, *it->second);
    g->insertMeta("units", openvdb::StringMetadata(units));
    out.push_back(g);
  };
  if (channels.ct) name_grid(grids.ct, "ct", "HU");
  if (channels.labels) name_grid(grids.labels, "labels", "id");
  name_grid(grids.rgb, "rgb", "rgb01");
  return out;
}

// The names of the grids named_grids gives for `channels`, in the same order.
std::vector<std::string> grid_names(const ExportChannels& channels) {
  std::vector<std::string> names;
  if (channels.ct) names.push_back("ct");
  if (channels.labels) names.push_back("labels");
  names.push_back("rgb");
  return names;
}

// One file written: its path, the level part it holds, the stack slices that part covers.
struct WrittenPart {
  std::string path;
  LevelPart part;
  SliceRange slices;
  std::uint64_t active = 0, leaves = 0, bytes = 0;
  double estimated_bytes = 0;
};

nlohmann::json part_json(const WrittenPart& w) {
  return {{"file", fs::path(w.path).filename().string()},
          {"slices", {w.slices.first, w.slices.last}},
          {"z", {w.part.z_first, w.part.z_last}},
          {"active_voxels", w.active},
          {"leaves", w.leaves},
          {"estimated_mb", w.estimated_bytes / (1024.0 * 1024.0)},
          {"bytes", w.bytes}};
}

// Builds the grids of `part` of the chosen level and writes them to `output` (atomically).
// `as_part`: the file is one part of the level (metadata "vispack_part_slices", "vispack_part_z").
WrittenPart write_level_part(const Config& config, const format::Reader& reader,
                             const VdbLevelChoice& choice, const ExportChannels& channels,
                             const LevelPart& part, bool as_part, SliceRange slices,
                             const std::string& output, int threads,
                             std::vector<std::string>* names_out) {
  const format::LevelInfo& info = reader.level(choice.level);
  ExportGrids grids = build_grids(reader, choice.level, channels, part, threads);
  const openvdb::MetaMap meta = export_metadata(config, info, choice, as_part, slices, part);
  const openvdb::GridPtrVec named = named_grids(grids, channels, meta);
  WrittenPart w;
  w.path = output;
  w.part = part;
  w.slices = slices;
  w.active = grids.active;
  w.leaves = grids.rgb->tree().leafCount();
  make_directories(fs::path(output).parent_path().string());
  // Written to a temporary name and renamed into place (removed on any failure); the write
  // system calls overlap OpenVDB's serialisation when a second thread is allowed.
  write_vdb_grids(output, openvdb::GridCPtrVec(named.begin(), named.end()), meta, threads > 1);
  w.bytes = std::uint64_t(fs::file_size(output));
  // Only the names leave: the grids go with this scope, before the next part is built.
  if (names_out) {
    names_out->clear();
    for (const auto& g : named)
      names_out->push_back(g->getName());
  }
  return w;
}

// The stage report of a written export (one file, a shard's part, or the parts of the level).
void report_export(StageRun& run, const Config& config, const std::string& output,
                   const VdbExportPlan& plan, const format::LevelInfo& info, bool sharded,
                   const std::vector<WrittenPart>& written, const std::vector<std::string>& grids) {
  const VdbLevelChoice& choice = plan.choice;
  run.set_report("output", output);
  std::uint64_t bytes = 0, active = 0, leaves = 0;
  for (const auto& w : written) {
    bytes += w.bytes;
    active += w.active;
    leaves += w.leaves;
  }
  run.set_report("output_bytes", bytes);
  if (sharded) {
    run.set_report("part_slices", {written[0].slices.first, written[0].slices.last});
    run.set_report("part_z", {written[0].part.z_first, written[0].part.z_last});
  }
  const bool parts = !plan.parts.empty();
  run.set_report("layout", parts ? "parts" : sharded ? "shard part" : "file");
  run.set_report("layout_reason",
                 parts || !sharded
                     ? plan.why
                     : plan.why + "; a shard (--slices) writes the part of it its slices cover");
  if (parts) {
    nlohmann::json list = nlohmann::json::array();
    for (const auto& w : written)
      list.push_back(part_json(w));
    run.set_report("parts", list);
  }
  const nlohmann::json names = grids;
  run.set_report("grids", names);
  run.set_report("level", choice.level);
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
}

// The part files an index lists (absolute), or empty when it is missing or unreadable.
std::vector<std::string> indexed_parts(const std::string& index) {
  std::vector<std::string> files;
  if (!fs::exists(index)) return files;
  try {
    const auto j = nlohmann::json::parse(read_file(index));
    for (const auto& p : j.at("parts"))
      files.push_back((fs::path(index).parent_path() / p.at("file").get<std::string>()).string());
  } catch (const std::exception&) {
    return {};
  }
  return files;
}

void remove_file(const std::string& path) {
  std::error_code ec;
  fs::remove(path, ec);
}

// The parts' index, "<vdb_output stem>.parts.json": how to open the export (merge the parts'
// grids of one name: their leaves are disjoint) and what each part holds. The header is all
// of it but "parts": the same for every process that follows the same plan (a shard's too).
nlohmann::json parts_index_header(const Config& config, const VdbExportPlan& plan,
                                  const format::LevelInfo& info,
                                  const std::vector<std::string>& grids) {
  const nlohmann::json names = grids;
  return {{"vispack_version", version_string()},
          {"source", fs::path(config.output).filename().string()},
          {"level", plan.choice.level},
          {"level_choice", plan.choice.automatic ? "auto" : "vdb.level"},
          {"dims", info.dims},
          {"voxel_size_mm", info.spacing_mm},
          {"origin_mm", info.origin_mm},
          {"grids", names},
          {"reason", plan.why},
          {"max_memory_mb", config.vdb.max_memory_mb},
          {"how_to_open",
           "each part is a complete OpenVDB file of the same grids, transform and metadata, "
           "holding the level's z range \"z\" (index space); the parts' leaves are disjoint, so "
           "merging the grids of one name (tree().merge) gives the whole level"}};
}

std::string parts_index_text(nlohmann::json header, const nlohmann::json& parts) {
  header["parts"] = parts;
  return header.dump(2) + "\n";
}

std::string parts_index_text(const nlohmann::json& header,
                             const std::vector<WrittenPart>& written) {
  nlohmann::json list = nlohmann::json::array();
  for (const auto& w : written)
    list.push_back(part_json(w));
  return parts_index_text(header, list);
}

// The file names of the plan's parts (what vdb_part_path gives for the slices each covers).
struct PlannedPart {
  VdbPartPlan plan;
  SliceRange covers;
  std::string path;
};

std::vector<PlannedPart> planned_parts(const Config& config, const VdbExportPlan& plan,
                                       std::int64_t depth, int stack) {
  std::vector<PlannedPart> out;
  for (const VdbPartPlan& p : plan.parts) {
    const SliceRange covers{slice_of_level_z(p.z_first, depth, stack),
                            slice_of_level_z(p.z_last, depth, stack)};
    out.push_back({p, covers, vdb_part_path(config, covers.first, covers.last)});
  }
  return out;
}

// Builds and writes one planned part (the grids freed before it returns).
WrittenPart write_planned_part(const Config& config, const format::Reader& reader,
                               const VdbLevelChoice& choice, const ExportChannels& channels,
                               const PlannedPart& p, StageRun& run,
                               std::vector<std::string>* names) {
  run.remove_stale_temporaries_of(p.path);
  const LevelPart part =
      level_part_z(reader, channels.rgba, choice.level, p.plan.z_first, p.plan.z_last);
  WrittenPart w = write_level_part(config, reader, choice, channels, part, true, p.covers, p.path,
                                   run.threads(), names);
  w.estimated_bytes = p.plan.bytes;
  // The part's grids are freed; glibc keeps much of it in the builder threads' arenas, which
  // the next part's threads did not reuse (2048x1216, two parts: the second peaked 40 % above
  // the first): hand it back before the next part is built.
  malloc_trim(0);
  return w;
}

void print_part(const StageOptions& options, std::size_t i, std::size_t n, const WrittenPart& w) {
  if (options.quiet) return;
  std::printf("vdb: part %zu/%zu: z %lld:%lld (slices %d:%d), %llu leaves -> %s\n", i + 1, n,
              (long long)w.part.z_first, (long long)w.part.z_last, w.slices.first, w.slices.last,
              (unsigned long long)w.leaves, w.path.c_str());
  std::fflush(stdout);
}

// A shard's record of one part it wrote, in its stage folder (work/vdb-parts/part-<file>.json):
// the plan's key (the packed file and the stage hash, from which the plan follows), the index
// header, the part count and the part's index entry. The shard that finds every part of the
// plan recorded (and its file there, of the recorded size) writes the index from them.
std::string part_record_path(const StageRun& run, const WrittenPart& w) {
  return run.dir() + "/part-" + fs::path(w.path).filename().string() + ".json";
}

// Writes the index from the records of `key` when they list every part of the plan, their files
// present: true when the index is complete (written now, or already holding that text).
bool complete_parts_index(const std::string& records_dir, const std::string& key,
                          const std::string& index) {
  std::optional<nlohmann::json> header;
  std::size_t count = 0;
  std::map<std::int64_t, nlohmann::json> parts;  // by first z
  std::error_code ec;
  for (fs::directory_iterator it(records_dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.rfind("part-", 0) != 0 || it->path().extension() != ".json") continue;
    try {
      const auto record = nlohmann::json::parse(read_file(it->path().string()));
      if (record.at("key") != key) continue;
      const auto& p = record.at("part");
      const fs::path file = fs::path(index).parent_path() / p.at("file").get<std::string>();
      std::error_code size_ec;
      if (fs::file_size(file, size_ec) != p.at("bytes").get<std::uint64_t>() || size_ec) continue;
      header = record.at("index");
      count = record.at("part_count").get<std::size_t>();
      parts[p.at("z").at(0).get<std::int64_t>()] = p;
    } catch (const std::exception&) {
      continue;  // a record being replaced, or not ours
    }
  }
  if (!header || parts.size() != count) return false;
  std::int64_t z = 0;
  nlohmann::json list = nlohmann::json::array();
  for (const auto& [z_first, p] : parts) {
    if (z_first != z) return false;
    z = p.at("z").at(1).get<std::int64_t>();
    list.push_back(p);
  }
  if (z != header->at("dims").at(2).get<std::int64_t>()) return false;
  const std::string text = parts_index_text(*header, list);
  std::error_code exists_ec;
  if (!fs::exists(index, exists_ec) || read_file(index) != text) write_file_atomic(index, text);
  return true;
}

// An index that another plan wrote (another level, budget, packed file or set of parts) goes
// before a shard writes its parts, with the parts it lists that this plan does not write.
void remove_stale_index(const std::string& index, const nlohmann::json& header,
                        const std::vector<PlannedPart>& planned) {
  std::error_code ec;
  if (!fs::exists(index, ec)) return;
  std::vector<std::string> files;
  for (const auto& p : planned)
    files.push_back(fs::path(p.path).filename().string());
  try {
    auto old = nlohmann::json::parse(read_file(index));
    std::vector<std::string> old_files;
    for (const auto& p : old.at("parts"))
      old_files.push_back(p.at("file").get<std::string>());
    old.erase("parts");
    if (old == header && old_files == files) return;  // this plan's index (a shard was first)
  } catch (const std::exception&) {
  }
  for (const auto& f : indexed_parts(index))
    if (std::find(files.begin(), files.end(), fs::path(f).filename().string()) == files.end())
      remove_file(f);
  remove_file(index);
}

// The export itself: run_vdb_stage runs it inside its TBB arena.
StageResult export_vdb(const Config& config, const StageOptions& options) {
  if (!config.vdb.enabled || config.vdb_output.empty())
    throw ConfigError(cat(config.path, ": vdb.enabled is false: no OpenVDB export configured"));
  // --slices A:B names stack indices (as every stage's); the export works in level-0 output z,
  // where stack slice k lies at its colour slot (a missing colour file is an empty slice of the
  // packed volume: slice_z.h). `stack` is the level-0 depth and `slices` the shard's output z
  // [slot of A, slot of B): shards that tile the stack tile it. Without a gap both are the stack
  // indices. Part files and records are named by output z.
  const std::vector<SliceFile> files = stack_slices(config);
  SliceRange given{0, int(files.size())};
  if (!options.slices.empty()) given = parse_slice_range(options.slices, int(files.size()));
  const bool sharded = given.first != 0 || given.last != int(files.size());
  const int stack = colour_slot_count(files);
  const SliceRange slices = colour_slots_of_stack_range(files, given);
  if (!fs::exists(config.output))
    throw InputError(cat(config.output,
                         ": packed file missing: vispack-vdb exports the packed "
                         "file's pyramid (run vispack-pack first)"));

  // Unsharded: one unit in work/vdb (the file, or the parts and their index). A shard: unit
  // `slices.first` of work/vdb-parts, whose outputs are its slices' part of a level that fits,
  // or the plan's parts that start in its slices (a shard's manifest records only its own).
  const std::string output =
      sharded ? vdb_part_path(config, slices.first, slices.last) : config.vdb_output;
  const std::string index = vdb_parts_index_path(config);
  Fingerprint fp;
  fp.file(config.output).text(output);
  if (sharded) fp.text(cat(slices.first, ":", slices.last));
  StageOptions unit = options;
  unit.slices = sharded ? cat(slices.first, ":", slices.last) : std::string();
  StageRun run(config, sharded ? "vdb-parts" : "vdb", sharded ? stack : 1, unit, {"vdb"});
  const int unit_index = sharded ? slices.first : 0;
  run.remove_stale_temporaries_of(output);
  const std::string input = fp.str();
  // The key of the shards' part records: the plan follows from the packed file and the stage
  // hash (the config's vdb section, the version) alone, so shards that agree on it agree on it.
  const std::string plan_key =
      Fingerprint().file(config.output).text(run.stage_hash()).text(cat(stack)).str();
  if (sharded) {
    if (run.up_to_date(unit_index, input, run.recorded_outputs(unit_index))) {
      run.skip(unit_index);
      const bool indexed = complete_parts_index(run.dir(), plan_key, index);
      return run.finish(indexed ? index : output);
    }
  } else if (run.up_to_date(unit_index, input, {output})) {
    run.skip(unit_index);
    return run.finish(output);
  }
  if (!sharded) {
    std::vector<std::string> outputs = indexed_parts(index);
    if (!outputs.empty()) {
      outputs.push_back(index);
      if (run.up_to_date(unit_index, input, outputs)) {
        run.skip(unit_index);
        return run.finish(index);
      }
    }
  }

  const format::Reader reader = format::Reader::open(config.output);
  // Every process, shard or not, plans the same export (the plan reads the whole packed file):
  // a shard writes its slices' part of a level that fits as one file, or the plan's parts that
  // start in its slices.
  VdbExportPlan plan = plan_vdb_export(config, reader, run.threads());
  const VdbLevelChoice& choice = plan.choice;
  const format::LevelInfo& info = reader.level(choice.level);
  const std::int64_t depth = info.dims[2];
  const std::string chosen = describe_vdb_choice(choice);
  const bool parts = !plan.parts.empty();
  const std::vector<PlannedPart> planned = planned_parts(config, plan, depth, stack);
  // A shard's level z range: [ceil(A * D / S), ceil(B * D / S)); the shards of a stack tile it.
  const std::int64_t shard_z0 = level_z_of_slice(slices.first, depth, stack);
  const std::int64_t shard_z1 = level_z_of_slice(slices.last, depth, stack);
  std::vector<std::size_t> mine;  // the planned parts this process writes
  for (std::size_t i = 0; i < planned.size(); ++i)
    if (planned[i].plan.z_first >= shard_z0 && planned[i].plan.z_first < shard_z1)
      mine.push_back(i);
  if (!options.quiet) {
    std::string what = parts ? cat(plan.parts.size(), " parts listed in ", index) : "one file";
    if (sharded)
      what +=
          parts ? cat("; slices ", slices.first, ":", slices.last, " (level z ", shard_z0, ":",
                      shard_z1, ") write ", mine.size(), " of them")
                : cat("; slices ", slices.first, ":", slices.last, " write their part to ", output);
    std::printf("vdb: exporting %s as %s (%s)\n", chosen.c_str(), what.c_str(), plan.why.c_str());
    std::fflush(stdout);
  }

  const ExportChannels channels = export_channels(reader);
  const nlohmann::json header = parts_index_header(config, plan, info, grid_names(channels));
  openvdb::initialize();
  // A voxel is active where the packed alpha (body coverage) is > 0: at level 0 of an
  // undownsampled file exactly the body mask.
  std::vector<WrittenPart> written;
  std::vector<std::string> named = grid_names(channels);  // the grids die with each part
  if (!parts) {
    const LevelPart part = level_part(reader, channels.rgba, choice.level, slices, stack);
    written.push_back(write_level_part(config, reader, choice, channels, part, sharded, slices,
                                       output, run.threads(), &named));
    if (!sharded) {  // parts of an earlier run at another budget would contradict the file
      for (const auto& f : indexed_parts(index))
        remove_file(f);
    }
    remove_file(index);  // a shard's part file may have the name of a part it lists
    run.done(unit_index, input, {output}, reader.file_size());
    report_export(run, config, output, plan, info, sharded, written, named);
    return run.finish(output);
  }

  // Parts: the index goes first (a set of parts without it is incomplete) and is written last;
  // a single file of an earlier run goes too. Shards keep an index of this same plan (another
  // shard may have completed it: the last one rewrites it).
  if (sharded) {
    remove_stale_index(index, header, planned);
  } else {
    const std::vector<std::string> stale = indexed_parts(index);
    remove_file(index);
    for (const auto& f : stale)
      if (std::none_of(planned.begin(), planned.end(),
                       [&](const PlannedPart& p) { return p.path == f; }))
        remove_file(f);
  }
  remove_file(config.vdb_output);
  std::vector<std::string> outputs;
  for (std::size_t n = 0; n < mine.size(); ++n) {
    const std::size_t i = mine[n];
    written.push_back(
        write_planned_part(config, reader, choice, channels, planned[i], run, &named));
    outputs.push_back(planned[i].path);
    if (sharded)
      write_file_atomic(part_record_path(run, written.back()),
                        nlohmann::json{{"key", plan_key},
                                       {"part_count", planned.size()},
                                       {"index", header},
                                       {"part", part_json(written.back())}}
                            .dump(2));
    print_part(options, i, planned.size(), written.back());
  }
  bool indexed = true;
  if (sharded) {
    run.done(unit_index, input, outputs, reader.file_size());
    indexed = complete_parts_index(run.dir(), plan_key, index);
    run.set_report("shard_z", {shard_z0, shard_z1});
    run.set_report("parts_planned", planned.size());
    run.set_report("index_complete", indexed);
  } else {
    write_file_atomic(index, parts_index_text(header, written));
    outputs.push_back(index);
    run.done(unit_index, input, outputs, reader.file_size());
  }
  report_export(run, config, index, plan, info, false, written, named);
  if (sharded) {
    run.set_report("shard_slices", {slices.first, slices.last});
    if (!options.quiet)
      std::printf("vdb: %s\n", indexed ? cat("every part written: ", index).c_str()
                                       : "the index waits for the other shards' parts");
  }
  return run.finish(indexed ? index : (outputs.empty() ? run.dir() : outputs.front()));
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

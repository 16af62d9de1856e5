#include "vispack/pipeline/vdb/vdb_level.h"

#include <algorithm>
#include <atomic>
#include <cstdio>

#include "vispack/common/error.h"
#include "vispack/common/parallel.h"

namespace vispack::pipeline {

namespace {

constexpr double kMiB = 1024.0 * 1024.0;

int rgba_channel(const format::Reader& reader) {
  const auto c = reader.find_channel("rgba");
  if (!c) throw InputError(cat(reader.path(), ": no \"rgba\" channel: nothing to export"));
  return *c;
}

std::string mb(double bytes) {
  char text[32];
  std::snprintf(text, sizeof text, "%.1f", bytes / kMiB);
  return text;
}

// The voxel extent of brick b along `axis` of a level (edge voxels, less at the far edge).
std::int64_t brick_extent(const format::LevelInfo& info, std::int64_t edge, int axis,
                          std::int64_t b) {
  return std::min(edge, info.dims[axis] - b * edge);
}

// The stored bytes of every brick of the level, all channels (what the export maps).
std::uint64_t level_stored_bytes(const format::Reader& reader, int level) {
  const auto& grid = reader.level(level).bricks;
  std::uint64_t bytes = 0;
  for (int c = 0; c < int(reader.channels().size()); ++c)
    for (std::int64_t bz = 0; bz < grid[2]; ++bz)
      for (std::int64_t by = 0; by < grid[1]; ++by)
        for (std::int64_t bx = 0; bx < grid[0]; ++bx)
          bytes += reader.brick(c, level, bx, by, bz).stored_size;
  return bytes;
}

// Lower bound on the active voxels without decoding: the voxels of uniform bricks (of the rgba
// `channel`) that lie wholly inside the body.
std::uint64_t uniform_inside_voxels(const format::Reader& reader, int channel, int level) {
  const format::LevelInfo& info = reader.level(level);
  const std::int64_t edge = reader.brick_edge();
  const auto& grid = info.bricks;
  std::uint64_t inside = 0;
  for (std::int64_t bz = 0; bz < grid[2]; ++bz)
    for (std::int64_t by = 0; by < grid[1]; ++by)
      for (std::int64_t bx = 0; bx < grid[0]; ++bx) {
        const format::BrickInfo& b = reader.brick(channel, level, bx, by, bz);
        if (b.codec == format::Codec::kUniform && b.uniform[3] > 0)
          inside +=
              std::uint64_t(brick_extent(info, edge, 0, bx) * brick_extent(info, edge, 1, by) *
                            brick_extent(info, edge, 2, bz));
      }
  return inside;
}

// The exact count: decodes the bricks on the body's edge and sets est's active_voxels,
// scanned_bytes and leaves. One flag per 8^3 leaf of the level. Bricks are multiples of 8
// voxels (pack.brick_edge is a power of two >= 8), so no leaf straddles two bricks and rows of
// bricks may run in parallel; another edge would let two rows write one flag, so it runs on one
// thread.
void count_active_leaves(const format::Reader& reader, int channel, int level, int threads,
                         VdbLevelEstimate& est) {
  const format::LevelInfo& info = reader.level(level);
  const std::int64_t edge = reader.brick_edge();
  const auto& grid = info.bricks;
  auto extent = [&](int axis, std::int64_t b) { return brick_extent(info, edge, axis, b); };
  const std::array<std::int64_t, 3> leaf_dims = {(info.dims[0] + 7) / 8, (info.dims[1] + 7) / 8,
                                                 (info.dims[2] + 7) / 8};
  std::vector<std::uint8_t> touched(std::size_t(leaf_dims[0] * leaf_dims[1] * leaf_dims[2]), 0);
  auto flag = [&](std::int64_t x, std::int64_t y, std::int64_t z) {
    touched[std::size_t(((z / 8) * leaf_dims[1] + y / 8) * leaf_dims[0] + x / 8)] = 1;
  };
  // Touched leaves per layer of 8 level z (the parts' planning, plan_vdb_parts): counted from
  // the flags after the scan.
  std::atomic<std::uint64_t> active{0}, scanned{0};
  const std::size_t brick_bytes = reader.brick_bytes(channel);
  parallel_for(grid[2] * grid[1], edge % 8 == 0 ? threads : 1, [&](std::int64_t row) {
    const std::int64_t bz = row / grid[1], by = row % grid[1];
    std::vector<std::uint8_t> buffer;
    std::uint64_t row_active = 0;
    for (std::int64_t bx = 0; bx < grid[0]; ++bx) {
      const format::BrickInfo& b = reader.brick(channel, level, bx, by, bz);
      if (b.max[3] == 0) continue;  // wholly outside the body
      const std::int64_t x0 = bx * edge, y0 = by * edge, z0 = bz * edge;
      const std::int64_t nx = extent(0, bx), ny = extent(1, by), nz = extent(2, bz);
      if (b.min[3] > 0) {  // wholly inside (uniform or not): every valid voxel is active
        row_active += std::uint64_t(nx * ny * nz);
        for (std::int64_t lz = z0 / 8; lz <= (z0 + nz - 1) / 8; ++lz)
          for (std::int64_t ly = y0 / 8; ly <= (y0 + ny - 1) / 8; ++ly)
            for (std::int64_t lx = x0 / 8; lx <= (x0 + nx - 1) / 8; ++lx)
              flag(lx * 8, ly * 8, lz * 8);
        continue;
      }
      scanned += b.stored_size;
      buffer.resize(brick_bytes);
      reader.decode_brick(b, buffer.data(), buffer.size());
      reader.release_payload_pages(b);  // the file's pages do not stay resident
      for (std::int64_t z = 0; z < nz; ++z)
        for (std::int64_t y = 0; y < ny; ++y) {
          const std::uint8_t* voxel = buffer.data() + 4 * std::size_t((z * edge + y) * edge);
          for (std::int64_t x = 0; x < nx; ++x)
            if (voxel[4 * x + 3] > 0) {
              ++row_active;
              flag(x0 + x, y0 + y, z0 + z);
            }
        }
    }
    active += row_active;
  });
  est.active_voxels = active.load();
  est.scanned_bytes = scanned.load();
  est.leaves_per_layer.assign(std::size_t(leaf_dims[2]), 0);
  const std::size_t layer = std::size_t(leaf_dims[0] * leaf_dims[1]);
  for (std::size_t l = 0; l < est.leaves_per_layer.size(); ++l)
    est.leaves_per_layer[l] = std::uint64_t(
        std::count(touched.begin() + std::ptrdiff_t(l * layer),
                   touched.begin() + std::ptrdiff_t((l + 1) * layer), std::uint8_t(1)));
  est.leaves = 0;
  for (const std::uint64_t n : est.leaves_per_layer)
    est.leaves += n;
}

}  // namespace

double vdb_bytes_per_leaf(const format::Reader& reader) {
  double bytes = kVdbLeafBytesVec3s;
  if (reader.find_channel("ct")) bytes += kVdbLeafBytesFloat;
  if (reader.find_channel("labels")) bytes += kVdbLeafBytesInt32;
  return bytes;
}

VdbLevelEstimate estimate_vdb_level(const format::Reader& reader, int level, int threads,
                                    double stop_above_bytes, std::uint64_t earlier_resident_bytes) {
  const int channel = rgba_channel(reader);
  const format::LevelInfo& info = reader.level(level);
  VdbLevelEstimate est;
  est.level = level;
  est.dims = info.dims;
  est.spacing_mm = info.spacing_mm;
  const double per_leaf = vdb_bytes_per_leaf(reader);
  est.mapped_bytes = level_stored_bytes(reader, level);
  const double fixed = kVdbFixedBytes + double(est.mapped_bytes) + double(earlier_resident_bytes);
  if (stop_above_bytes > 0) {
    // Lower bound without decoding: uniform bricks wholly inside the body fill at least
    // voxels / 512 leaves.
    const std::uint64_t inside = uniform_inside_voxels(reader, channel, level);
    est.active_voxels = inside;
    est.leaves = (inside + 511) / 512;
    est.bytes = fixed + double(est.leaves) * per_leaf;
    if (est.bytes > stop_above_bytes) {
      est.exact = false;
      return est;
    }
  }
  count_active_leaves(reader, channel, level, threads, est);
  est.bytes = fixed + double(est.leaves) * per_leaf;
  return est;
}

VdbLevelChoice choose_vdb_level(const Config& config, const format::Reader& reader, int threads) {
  VdbLevelChoice choice;
  choice.budget_bytes = double(config.vdb.max_memory_mb) * kMiB;
  const int levels = reader.level_count();
  if (config.vdb.level) {
    choice.automatic = false;
    choice.level = *config.vdb.level;
    if (choice.level >= levels)
      throw ConfigError(cat(config.path, ": vdb.level: ", choice.level, ": the packed file ",
                            reader.path(), " has levels 0..", levels - 1));
    choice.estimates.push_back(
        estimate_vdb_level(reader, choice.level, threads, choice.budget_bytes));
    if (choice.chosen().bytes > choice.budget_bytes)
      throw ConfigError(cat(config.path, ": vdb.level: ", describe_vdb_choice(choice),
                            ": does not fit vdb.max_memory_mb (raise it, or choose a coarser "
                            "level or \"auto\")"));
    return choice;
  }
  std::uint64_t resident = 0;  // rgba pages of finer levels that the estimates decoded
  for (int level = 0; level < levels; ++level) {
    choice.level = level;
    choice.estimates.push_back(
        estimate_vdb_level(reader, level, threads, choice.budget_bytes, resident));
    if (choice.chosen().bytes <= choice.budget_bytes) return choice;
    resident += choice.chosen().scanned_bytes;
  }
  throw ConfigError(cat(config.path, ": vdb.max_memory_mb: even the coarsest ",
                        describe_vdb_choice(choice), ": does not fit (raise vdb.max_memory_mb)"));
}

double vdb_part_bytes(const format::Reader& reader, std::uint64_t leaves) {
  return kVdbFixedBytes + double(leaves) * vdb_bytes_per_leaf(reader);
}

std::vector<VdbPartPlan> plan_vdb_parts(const format::Reader& reader, const VdbLevelEstimate& est,
                                        double budget_bytes) {
  if (!est.exact || est.leaves_per_layer.empty())
    throw std::logic_error("plan_vdb_parts needs an exact estimate with its leaf layers");
  const std::int64_t depth = est.dims[2], edge = reader.brick_edge();
  const auto layers_bytes = [&](std::int64_t z0, std::int64_t z1) {  // leaf layers of [z0, z1)
    std::uint64_t leaves = 0;
    for (std::int64_t l = z0 / 8; l < (z1 + 7) / 8; ++l)
      leaves += est.leaves_per_layer[std::size_t(l)];
    return leaves;
  };
  std::vector<VdbPartPlan> parts;
  std::int64_t z = 0;
  while (z < depth) {
    VdbPartPlan part;
    part.z_first = z;
    std::int64_t end = z;
    std::uint64_t leaves = 0;
    // Whole brick rows while they fit (each brick decoded once), else leaf layers of one row.
    while (end < depth) {
      const std::int64_t row_end = std::min(depth, (end / edge + 1) * edge);
      const std::uint64_t row = layers_bytes(end, row_end);
      if (vdb_part_bytes(reader, leaves + row) <= budget_bytes) {
        leaves += row;
        end = row_end;
        continue;
      }
      if (end == z) {
        // One brick row alone is over the budget: as many leaf layers of it as fit.
        while (end < row_end) {
          const std::int64_t layer_end = std::min(row_end, (end / 8 + 1) * 8);
          const std::uint64_t layer = layers_bytes(end, layer_end);
          if (vdb_part_bytes(reader, leaves + layer) > budget_bytes) break;
          leaves += layer;
          end = layer_end;
        }
      }
      break;
    }
    if (end == z) return {};  // one layer of 8 z alone is over the budget
    part.z_last = end;
    part.leaves = leaves;
    part.bytes = vdb_part_bytes(reader, leaves);
    parts.push_back(part);
    z = end;
  }
  return parts;
}

VdbExportPlan plan_vdb_export(const Config& config, const format::Reader& reader, int threads) {
  VdbExportPlan plan;
  if (config.vdb.layout == VdbLayout::kFile) {
    plan.choice = choose_vdb_level(config, reader, threads);
    plan.why = plan.choice.automatic
                   ? "vdb.layout \"file\": the finest level within vdb.max_memory_mb"
                   : "vdb.level, vdb.layout \"file\"";
    return plan;
  }
  VdbLevelChoice& choice = plan.choice;
  choice.budget_bytes = double(config.vdb.max_memory_mb) * kMiB;
  choice.automatic = !config.vdb.level;
  const int levels = reader.level_count();
  const int first = config.vdb.level.value_or(0);
  if (first >= levels)
    throw ConfigError(cat(config.path, ": vdb.level: ", first, ": the packed file ", reader.path(),
                          " has levels 0..", levels - 1));
  for (int level = first; level < levels; ++level) {
    choice.level = level;
    choice.estimates.push_back(estimate_vdb_level(reader, level, threads));
    const VdbLevelEstimate& est = choice.chosen();
    if (est.bytes <= choice.budget_bytes) {
      plan.why =
          cat(choice.automatic ? "level 0" : "vdb.level", " fits vdb.max_memory_mb: one file");
      return plan;
    }
    plan.parts = plan_vdb_parts(reader, est, choice.budget_bytes);
    if (!plan.parts.empty()) {
      plan.why = cat(choice.automatic ? "level 0" : "vdb.level", " needs ", mb(est.bytes),
                     " MB as one file, over vdb.max_memory_mb ", mb(choice.budget_bytes),
                     " MB: ", plan.parts.size(), " parts (z slabs), each within it");
      return plan;
    }
    if (!choice.automatic) break;
  }
  if (!choice.automatic)
    throw ConfigError(cat(config.path, ": vdb.level: ", describe_vdb_choice(choice),
                          ": does not fit vdb.max_memory_mb, not even as parts of 8 z slices "
                          "(raise it, or choose a coarser level or \"auto\")"));
  throw ConfigError(
      cat(config.path, ": vdb.max_memory_mb: even the coarsest ", describe_vdb_choice(choice),
          ": does not fit, not even as parts of 8 z slices (raise vdb.max_memory_mb)"));
}

std::string describe_vdb_choice(const VdbLevelChoice& choice) {
  const VdbLevelEstimate& e = choice.chosen();
  const char* bound = e.exact ? "" : "at least ";
  return cat("level ", e.level, " (", e.dims[0], " x ", e.dims[1], " x ", e.dims[2], " voxels of ",
             e.spacing_mm[0], " x ", e.spacing_mm[1], " x ", e.spacing_mm[2], " mm), ", bound,
             e.active_voxels, " active voxels in ", bound, e.leaves, " leaves, estimate ", bound,
             mb(e.bytes), " MB of budget ", mb(choice.budget_bytes), " MB");
}

}  // namespace vispack::pipeline

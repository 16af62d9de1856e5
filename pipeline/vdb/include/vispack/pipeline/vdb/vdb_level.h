// Which pyramid level of a packed file the OpenVDB export (vdb.h) can afford (docs/BENCHMARKS.md,
// 'OpenVDB export memory under a budget').
//
// OpenVDB keeps a grid's active voxels in 8^3 leaf nodes that store all 512 values once any one
// is set, so the memory of the export is (touched leaves) x (bytes per leaf of each grid) plus a
// fixed overhead; it does not depend on how full the touched leaves are. estimate_vdb_level
// counts the touched leaves of one level exactly: a voxel is active where the packed colour's
// alpha (body coverage) is > 0, the rule the export uses. It reads only the rgba channel, brick
// by brick (uniform bricks from the index, without decoding), so it holds one decoded brick and a
// flag per leaf (dims / 8 bytes: 9 MB for the NLM male's level 0) at a time.
// choose_vdb_level applies config vdb.level / vdb.max_memory_mb to those estimates.
// Thread-safety: free functions on a const Reader (which is thread-safe); no shared state.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "vispack/format/reader.h"
#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline {

// Measured resident bytes per leaf node (OpenVDB 10.0, Debian 12, glibc malloc): a dense 512^3
// block of each grid type built with a ValueAccessor in its own process, VmRSS after minus
// before, divided by tree().leafCount() (262144 leaves): float 2187.2, int32 2187.5, Vec3s
// 6292.6 (memUsage() says 2153.3 / 2153.3 / 6258.3; the rest is malloc's header per buffer).
// Writing the grids with io::File (Blosc/zip, one leaf buffer at a time) raised the peak by
// 4 MB for 262144 leaves, so the write needs no term of its own.
inline constexpr double kVdbLeafBytesFloat = 2188;
inline constexpr double kVdbLeafBytesInt32 = 2188;
inline constexpr double kVdbLeafBytesVec3s = 6293;
// Everything else the process holds while it exports, besides the level's payload pages of the
// memory-mapped .vpk (counted separately, VdbLevelEstimate::mapped_bytes: clean file pages that
// the kernel counts as resident once read): the libraries (vispack-vdb --help peaks at 136 MB
// resident), the leaf flags, decoded bricks. Measured: peak RSS of vispack-vdb minus the leaf and
// mapped terms, 145 MB on the small phantom (docs/BENCHMARKS.md "OpenVDB export memory under a
// budget" for the vhp ones).
inline constexpr double kVdbFixedBytes = 160.0 * 1024 * 1024;

// The estimate for one level.
struct VdbLevelEstimate {
  int level = 0;
  std::array<std::int64_t, 3> dims{0, 0, 0};
  std::array<double, 3> spacing_mm{0, 0, 0};
  std::uint64_t active_voxels = 0;  // alpha > 0 (a lower bound when !exact)
  std::uint64_t leaves = 0;         // touched 8^3 leaves (a lower bound when !exact)
  std::uint64_t mapped_bytes = 0;   // stored payload bytes of the level's bricks (all channels)
  std::uint64_t scanned_bytes = 0;  // rgba payload bytes this estimate decoded (now resident)
  // Estimated peak resident bytes of the export:
  // kVdbFixedBytes + leaves * vdb_bytes_per_leaf + mapped_bytes + earlier_resident_bytes.
  double bytes = 0;
  bool exact = true;  // false: only the lower bound from uniform bricks was computed (it
                      // already exceeded the budget, so the level was not decoded)
  // Touched leaves per layer of 8 level z slices (layer l: z in [8 l, 8 l + 8)); exact only.
  std::vector<std::uint64_t> leaves_per_layer;
};

// Bytes per touched leaf for the grids the export writes from `reader` (rgb always, ct and labels
// when the file has those channels).
double vdb_bytes_per_leaf(const format::Reader& reader);

// Counts the active voxels and touched leaves of `level` (decodes the level's non-uniform rgba
// bricks on `threads` threads). With `stop_above_bytes` > 0, first computes the lower bound that
// uniform all-inside bricks give and returns it (exact = false) without decoding when it already
// exceeds that many bytes. `earlier_resident_bytes`: mapped pages that earlier estimates of finer
// levels made resident (their scanned_bytes; a process's resident set keeps them), added to the
// estimate. Throws std::out_of_range for a bad level, FormatError for a brick that does not
// decode, InputError when the file has no "rgba" channel.
VdbLevelEstimate estimate_vdb_level(const format::Reader& reader, int level, int threads,
                                    double stop_above_bytes = 0,
                                    std::uint64_t earlier_resident_bytes = 0);

// The level to export and the estimates that led to it.
struct VdbLevelChoice {
  int level = 0;
  bool automatic = true;  // chosen by the budget (vdb.level unset or "auto")
  double budget_bytes = 0;
  std::vector<VdbLevelEstimate> estimates;  // finest first, up to and including `level`
  const VdbLevelEstimate& chosen() const { return estimates.back(); }
};

// vdb.level set: that level; ConfigError naming the config file, vdb.level, the estimate and the
// budget when it does not fit vdb.max_memory_mb, or when the file has no such level.
// Unset: the finest level whose estimate fits; ConfigError naming the coarsest level's estimate
// and the budget when none fits. `config` gives the options and the file name for messages.
VdbLevelChoice choose_vdb_level(const Config& config, const format::Reader& reader, int threads);

// One part of a level written as parts: level z in [z_first, z_last) (multiples of 8 but the
// last, so no OpenVDB leaf straddles two parts), its touched leaves and estimated peak bytes.
struct VdbPartPlan {
  std::int64_t z_first = 0, z_last = 0;
  std::uint64_t leaves = 0;
  double bytes = 0;
};

// Estimated peak resident bytes of an export that holds `leaves` touched leaves of the grids
// `reader`'s channels give: kVdbFixedBytes + leaves * vdb_bytes_per_leaf (the payload pages
// are released after each brick is decoded, so no mapped term).
double vdb_part_bytes(const format::Reader& reader, std::uint64_t leaves);

// Consecutive z slabs that tile the estimated level, each of at most `budget_bytes` by
// vdb_part_bytes: whole brick rows (each brick decoded once) while they fit, else the leaf
// layers of one row. Empty when one layer of 8 z alone is over the budget. `est` must be
// exact (logic_error otherwise).
std::vector<VdbPartPlan> plan_vdb_parts(const format::Reader& reader, const VdbLevelEstimate& est,
                                        double budget_bytes);

// What the export writes: one level, as one file (parts empty) or as parts, and why.
struct VdbExportPlan {
  VdbLevelChoice choice;
  std::vector<VdbPartPlan> parts;  // empty: one file
  std::string why;                 // "level 0 needs 10.5 GB as one file, over ... : 6 parts"
};

// vdb.layout "file": choose_vdb_level, one file. "auto": the level (vdb.level, or 0) as one
// file when its estimate fits vdb.max_memory_mb, else as plan_vdb_parts' parts; with vdb.level
// unset and not even one layer of 8 z of a level within the budget, the next coarser level.
// ConfigError (naming the config file, the key, the estimate and the budget) when nothing fits
// or the file has no such level.
VdbExportPlan plan_vdb_export(const Config& config, const format::Reader& reader, int threads);

// "level 1 (1024 x 608 x 48 voxels of 1 x 1 x 2 mm), 812345 active voxels in 2345 leaves,
// estimate 123.4 MB of budget 8192 MB" (MB = MiB) for messages and the stage's stdout line.
std::string describe_vdb_choice(const VdbLevelChoice& choice);

}  // namespace vispack::pipeline

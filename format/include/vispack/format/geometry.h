// Level and brick geometry of a packed volume (format/SPEC.md "Levels of detail", "Bricks",
// "Brick index"), computed in one place for the writer and the reader.
//
// Level 0 has the volume's dims; level L + 1 halves every dim of level L, rounding up; levels
// are added until the whole last level fits in one brick. Each level is cut into
// ceil(dims / brick_edge) bricks per axis. The brick index is ordered (level, channel, bz, by,
// bx), bx fastest. Units: voxels, bricks; spacing and origin in mm. Pure functions, no state.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <vector>

namespace vispack::format {

// Geometry of one level of the pyramid. Level L voxel i covers level-0 voxels
// [i * 2^L, (i + 1) * 2^L) on each axis (clipped to the volume).
struct LevelInfo {
  std::array<std::int64_t, 3> dims{0, 0, 0};    // voxels: ceil(dims0 / 2^L)
  std::array<std::int64_t, 3> bricks{0, 0, 0};  // brick grid: ceil(dims / brick_edge)
  std::array<double, 3> spacing_mm{1, 1, 1};    // spacing0 * 2^L
  std::array<double, 3> origin_mm{0, 0, 0};     // origin0 + (2^L - 1) / 2 * spacing0
};

// The whole pyramid and where each level's bricks start in the index.
struct VolumeGeometry {
  int brick_edge = 0;
  int channel_count = 0;
  std::vector<LevelInfo> levels;
  std::vector<std::uint64_t> level_base;  // index entry of (level, channel 0, brick 0,0,0)
  std::uint64_t index_count = 0;          // entries over all levels and channels

  // Bricks of one channel at `level` (gx * gy * gz).
  std::uint64_t bricks_per_channel(int level) const;
  // Position in the index of brick (bx, by, bz) of `channel` at `level`. No range checks:
  // the caller has checked level, channel and brick against `levels`.
  std::uint64_t entry(int level, int channel, std::int64_t bx, std::int64_t by,
                      std::int64_t bz) const;
};

// Number of levels for `dims` (each >= 1) with bricks of `brick_edge` (>= 1).
int level_count_for(const std::array<std::int64_t, 3>& dims, int brick_edge);

// The geometry of a volume; nullopt when the index would hold more than `max_index_entries`
// entries (or its size overflows). Preconditions: dims >= 1, brick_edge >= 1, channels >= 1.
std::optional<VolumeGeometry> make_geometry(const std::array<std::int64_t, 3>& dims,
                                            const std::array<double, 3>& spacing_mm,
                                            const std::array<double, 3>& origin_mm, int brick_edge,
                                            int channel_count, std::uint64_t max_index_entries);

}  // namespace vispack::format

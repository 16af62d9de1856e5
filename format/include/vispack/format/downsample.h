// The mip-pyramid reduction rules (SPEC.md "Levels of detail"): per-voxel rules, and the slice
// kernel the writer builds its pyramid with. Part of the format core, so every tool that
// reduces voxels (the writer, the pipeline's pack.downsample, tests) uses the same rules.
// All rounding is exact integer arithmetic, so every implementation agrees bit for bit.
// Pure functions, no state; safe to call from any thread.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

#include "vispack/format/types.h"

namespace vispack {
class ZeroPagedBuffer;
}

namespace vispack::format {

// Mean of `count` (1..8) int16 values, rounded half up: floor((2 * sum + n) / (2 * n)).
std::int16_t reduce_mean_i16(const std::int16_t* children, int count);

// Alpha-weighted mean of `count` (1..8) rgba8 voxels (children interleaved r, g, b, a):
//   alpha = floor((2 * sum(a) + n) / (2 * n));
//   colour = floor((2 * sum(c * a) + A) / (2 * A)) with A = sum(a) when A > 0, so a child of
//   alpha 0 (gel, outside the body) never tints the colour of a tissue voxel;
//   colour = the plain rounded mean when every alpha is 0.
std::array<std::uint8_t, 4> reduce_rgba_alpha_weighted(const std::uint8_t* children, int count);

// THE majority rule of vispack (the pyramid's label levels and pack.downsample's label blocks):
// the most frequent ID among `count` >= 1 IDs (any count: 2x2x2 children or an f x f block).
// Tie-break: among IDs of equal count, a non-zero ID wins over 0 (unlabelled), then the
// smallest ID wins. Examples: {0, 0, 5, 5} -> 5; {7, 3, 7, 3} -> 3; {0, 0, 0, 5, 5} -> 0.
// The result is always one of the inputs. Up to 8 IDs it allocates nothing; above, it sorts a
// copy (allocates).
std::uint16_t reduce_majority(const std::uint16_t* ids, std::size_t count);

// Reduces one output slice of the next level: `src` holds `src_slices` (1 or 2) consecutive
// slices of `dx` x `dy` voxels of `type` (x fastest, voxels of channel_type_bytes(type) bytes);
// `dst` receives ceil(dx / 2) x ceil(dy / 2) voxels, each reduced from its (up to 8) children
// with the rule of its type (rgba8: alpha-weighted mean, int16: mean, labels: majority).
// Rows are split over `threads` threads (parallel_for) on large slices; the result does not
// depend on `threads`. With `zeros` (the buffer `src` lies in), runs of output voxels whose
// children all lie in pages it knows to be zero are written as zeros without reading those pages
// (the reduction of zeros is zero under every rule), so they are never faulted in; the result is
// the same.
void downsample_slice(ChannelType type, const std::uint8_t* src, int src_slices, std::int64_t dx,
                      std::int64_t dy, std::uint8_t* dst, int threads,
                      const ZeroPagedBuffer* zeros = nullptr);

}  // namespace vispack::format

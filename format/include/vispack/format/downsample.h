// The mip-pyramid reduction rules (SPEC.md "Levels of detail"), exposed for tests and for
// tools that build pyramids of their own. Each function reduces the 2x2x2 children of one
// parent voxel; `count` children (1..8) exist (a parent on the far edge of an odd dim has
// fewer). All rounding is exact integer arithmetic, so every implementation agrees bit for bit.
#pragma once

#include <array>
#include <cstdint>

namespace vispack::format {

// Mean of int16 values, rounded half up: floor((2 * sum + n) / (2 * n)).
std::int16_t reduce_mean_i16(const std::int16_t* children, int count);

// Alpha-weighted mean of rgba8 voxels (children interleaved r, g, b, a):
//   alpha = floor((2 * sum(a) + n) / (2 * n));
//   colour = floor((2 * sum(c * a) + A) / (2 * A)) with A = sum(a) when A > 0, so a child of
//   alpha 0 (gel, outside the body) never tints the colour of a tissue voxel;
//   colour = the plain rounded mean when every alpha is 0.
std::array<std::uint8_t, 4> reduce_rgba_alpha_weighted(const std::uint8_t* children, int count);

// Majority of label IDs: the most frequent ID among the children; a tie goes to a non-zero
// ID over 0, then to the smallest ID. The result is always one of the children.
std::uint16_t reduce_majority(const std::uint16_t* children, int count);

}  // namespace vispack::format

#include "vispack/format/geometry.h"

#include <cmath>
#include <limits>

#include "int_math.h"

namespace vispack::format {
namespace {

using detail::ceil_div;
using detail::mul;

}  // namespace

std::uint64_t VolumeGeometry::bricks_per_channel(int level) const {
  const LevelInfo& li = levels[std::size_t(level)];
  return std::uint64_t(li.bricks[0]) * std::uint64_t(li.bricks[1]) * std::uint64_t(li.bricks[2]);
}

std::uint64_t VolumeGeometry::entry(int level, int channel, std::int64_t bx, std::int64_t by,
                                    std::int64_t bz) const {
  const LevelInfo& li = levels[std::size_t(level)];
  return level_base[std::size_t(level)] + std::uint64_t(channel) * bricks_per_channel(level) +
         std::uint64_t((bz * li.bricks[1] + by) * li.bricks[0] + bx);
}

int level_count_for(const std::array<std::int64_t, 3>& dims, int brick_edge) {
  int levels = 1;
  std::array<std::int64_t, 3> d = dims;
  while (d[0] > brick_edge || d[1] > brick_edge || d[2] > brick_edge) {
    for (auto& v : d)
      v = ceil_div(v, 2);
    ++levels;
  }
  return levels;
}

std::optional<VolumeGeometry> make_geometry(const std::array<std::int64_t, 3>& dims,
                                            const std::array<double, 3>& spacing_mm,
                                            const std::array<double, 3>& origin_mm, int brick_edge,
                                            int channel_count, std::uint64_t max_index_entries) {
  VolumeGeometry g;
  g.brick_edge = brick_edge;
  g.channel_count = channel_count;
  std::array<std::int64_t, 3> d = dims;
  std::uint64_t total = 0;
  for (int l = 0;; ++l) {
    LevelInfo li;
    li.dims = d;
    const double f = std::ldexp(1.0, l);
    for (int a = 0; a < 3; ++a) {
      li.bricks[a] = ceil_div(d[a], brick_edge);
      li.spacing_mm[a] = spacing_mm[a] * f;
      li.origin_mm[a] = origin_mm[a] + (f - 1) / 2 * spacing_mm[a];
    }
    auto n = mul(std::uint64_t(li.bricks[0]), std::uint64_t(li.bricks[1]));
    if (n) n = mul(*n, std::uint64_t(li.bricks[2]));
    if (n) n = mul(*n, std::uint64_t(channel_count));
    if (!n || *n > max_index_entries - total) return std::nullopt;
    g.level_base.push_back(total);
    total += *n;
    g.levels.push_back(li);
    if (d[0] <= brick_edge && d[1] <= brick_edge && d[2] <= brick_edge) break;
    for (auto& v : d)
      v = ceil_div(v, 2);
  }
  g.index_count = total;
  return g;
}

}  // namespace vispack::format

#include "vispack/render/volume.h"

#include <algorithm>
#include <cstring>
#include <stdexcept>

#include "vispack/common/error.h"

namespace vispack::render {

const char* channel_name(Channel c) {
  switch (c) {
    case Channel::kRgba:
      return "rgba";
    case Channel::kCt:
      return "ct";
    case Channel::kLabels:
      return "labels";
  }
  return "?";
}

int channel_bytes(Channel c) {
  return c == Channel::kRgba ? 4 : 2;
}

std::array<std::int64_t, 3> brick_grid(const VolumeSource& source, int level) {
  LevelGeometry g = source.level(level);
  std::int64_t e = std::max(1, source.brick_edge());
  return {(g.dims[0] + e - 1) / e, (g.dims[1] + e - 1) / e, (g.dims[2] + e - 1) / e};
}

Region brick_region(const VolumeSource& source, int level, const std::array<std::int64_t, 3>& b) {
  LevelGeometry g = source.level(level);
  std::int64_t e = std::max(1, source.brick_edge());
  Region r;
  for (int a = 0; a < 3; ++a) {
    if (b[a] < 0 || b[a] * e >= g.dims[a])
      throw std::out_of_range(cat(source.name(), ": brick outside level ", level));
    r.offset[a] = b[a] * e;
    r.size[a] = std::min(e, g.dims[a] - r.offset[a]);
  }
  return r;
}

BrickStats VolumeSource::brick_stats(Channel c, int level,
                                     const std::array<std::int64_t, 3>& brick) const {
  Region r = brick_region(*this, level, brick);
  std::vector<std::uint8_t> buf(std::size_t(r.voxels()) * std::size_t(channel_bytes(c)));
  read_region(c, level, r, buf.data());
  return compute_brick_stats(c, buf.data(), std::size_t(r.voxels()));
}

BrickStats compute_brick_stats(Channel c, const std::uint8_t* buf, std::size_t n) {
  BrickStats s;
  if (n == 0) return s;
  if (c == Channel::kRgba) {
    // Byte accumulators, 16 voxels' components side by side: the loop vectorises (a lost
    // slice's bricks are ranged this way when the brick tree is built).
    std::uint8_t lo[64], hi[64];
    std::fill(lo, lo + 64, std::uint8_t(255));
    std::fill(hi, hi + 64, std::uint8_t(0));
    std::size_t i = 0;
    for (; i + 16 <= n; i += 16) {
      const std::uint8_t* p = buf + 4 * i;
      for (int k = 0; k < 64; ++k) {
        const std::uint8_t v = p[k];
        lo[k] = v < lo[k] ? v : lo[k];
        hi[k] = v > hi[k] ? v : hi[k];
      }
    }
    for (; i < n; ++i)
      for (int k = 0; k < 4; ++k) {
        lo[k] = std::min(lo[k], buf[4 * i + std::size_t(k)]);
        hi[k] = std::max(hi[k], buf[4 * i + std::size_t(k)]);
      }
    for (int k = 0; k < 4; ++k) {
      s.min[k] = 255;
      s.max[k] = 0;
      for (int j = k; j < 64; j += 4) {
        s.min[k] = std::min<std::int64_t>(s.min[k], lo[j]);
        s.max[k] = std::max<std::int64_t>(s.max[k], hi[j]);
      }
    }
  } else if (c == Channel::kCt) {
    const auto* v = reinterpret_cast<const std::int16_t*>(buf);
    auto mm = std::minmax_element(v, v + n);
    s.min[0] = *mm.first;
    s.max[0] = *mm.second;
  } else {
    const auto* v = reinterpret_cast<const std::uint16_t*>(buf);
    std::vector<bool> seen(65536, false);
    for (std::size_t i = 0; i < n; ++i)
      seen[v[i]] = true;
    for (std::uint32_t id = 0; id < 65536; ++id)
      if (seen[id]) s.labels.push_back(id);
    s.min[0] = s.labels.front();
    s.max[0] = s.labels.back();
  }
  return s;
}

VolumeData load_level(const VolumeSource& source, int level) {
  VolumeData data;
  data.geometry = source.level(level);
  data.label_table = source.labels();
  Region all;
  all.size = data.geometry.dims;
  std::size_t n = std::size_t(data.geometry.voxels());
  if (source.has_channel(Channel::kRgba)) {
    data.rgba.resize(n * 4);
    source.read_region(Channel::kRgba, level, all, data.rgba.data());
  }
  if (source.has_channel(Channel::kCt)) {
    data.ct.resize(n);
    source.read_region(Channel::kCt, level, all, data.ct.data());
  }
  if (source.has_channel(Channel::kLabels)) {
    data.labels.resize(n);
    source.read_region(Channel::kLabels, level, all, data.labels.data());
  }
  return data;
}

MemorySource::MemorySource(std::shared_ptr<const VolumeData> data, int brick_edge)
    : data_(std::move(data)), brick_edge_(brick_edge > 0 ? brick_edge : 32) {
  if (!data_) throw std::invalid_argument("MemorySource: null volume");
  std::size_t n = std::size_t(data_->geometry.voxels());
  if ((!data_->rgba.empty() && data_->rgba.size() != 4 * n) ||
      (!data_->ct.empty() && data_->ct.size() != n) ||
      (!data_->labels.empty() && data_->labels.size() != n))
    throw std::invalid_argument("MemorySource: channel sizes do not match the dims");
}

LevelGeometry MemorySource::level(int level) const {
  if (level != 0) throw std::out_of_range(cat("memory volume: no level ", level));
  return data_->geometry;
}

void MemorySource::read_region(Channel c, int level, const Region& r, void* out) const {
  const LevelGeometry& g = data_->geometry;
  if (level != 0) throw std::out_of_range(cat("memory volume: no level ", level));
  if (!data_->has(c)) throw std::out_of_range(cat("memory volume: no channel ", channel_name(c)));
  for (int a = 0; a < 3; ++a)
    if (r.offset[a] < 0 || r.size[a] < 0 || r.offset[a] + r.size[a] > g.dims[a])
      throw std::out_of_range("memory volume: region outside the level");
  const std::uint8_t* src =
      c == Channel::kRgba
          ? data_->rgba.data()
          : (c == Channel::kCt ? reinterpret_cast<const std::uint8_t*>(data_->ct.data())
                               : reinterpret_cast<const std::uint8_t*>(data_->labels.data()));
  std::size_t bpv = std::size_t(channel_bytes(c));
  auto* dst = static_cast<std::uint8_t*>(out);
  for (std::int64_t z = 0; z < r.size[2]; ++z)
    for (std::int64_t y = 0; y < r.size[1]; ++y) {
      std::int64_t s = data_->index(r.offset[0], r.offset[1] + y, r.offset[2] + z);
      std::memcpy(dst + bpv * std::size_t((z * r.size[1] + y) * r.size[0]), src + bpv * s,
                  bpv * std::size_t(r.size[0]));
    }
}

}  // namespace vispack::render

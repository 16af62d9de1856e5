#include "vispack/render/brick_reader.h"

#include <algorithm>
#include <cstring>
#include <future>
#include <list>
#include <mutex>
#include <unordered_map>

#include "vispack/common/error.h"

namespace vispack::render {

namespace {
using Decoded = std::shared_ptr<const std::vector<std::uint8_t>>;
struct CacheKey {
  int channel;
  BrickKey key;
  bool operator==(const CacheKey& o) const { return channel == o.channel && key == o.key; }
};
struct CacheKeyHash {
  std::size_t operator()(const CacheKey& k) const {
    return BrickKeyHash()(k.key) ^ (std::size_t(k.channel) << 60);
  }
};
}  // namespace

struct BorderedBrickReader::Impl {
  std::int64_t capacity;
  mutable std::mutex mutex;
  struct Entry {
    std::shared_future<Decoded> future;
    std::list<CacheKey>::iterator lru;
    std::int64_t bytes = 0;
  };
  std::unordered_map<CacheKey, Entry, CacheKeyHash> map;
  std::list<CacheKey> lru;  // front = most recent
  std::int64_t bytes = 0;
  std::int64_t decoded = 0;
};

BorderedBrickReader::BorderedBrickReader(const VolumeSource& source, int border,
                                         std::int64_t cache_bytes)
    : source_(source), border_(std::max(0, border)), impl_(std::make_unique<Impl>()) {
  impl_->capacity = std::max<std::int64_t>(cache_bytes, 0);
}
BorderedBrickReader::~BorderedBrickReader() = default;

std::int64_t BorderedBrickReader::decoded() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->decoded;
}

BorderedBrick BorderedBrickReader::read(Channel c, const BrickKey& key) const {
  Impl& s = *impl_;
  const LevelGeometry g = source_.level(key.level);
  const auto grid = brick_grid(source_, key.level);
  const std::int64_t e = std::max(1, source_.brick_edge());
  const Region centre = brick_region(source_, key.level, key.brick);
  const std::size_t bpv = std::size_t(channel_bytes(c));

  // The decoded neighbours (3×3×3 slots, null outside the grid or when they fail to decode).
  Decoded slots[27];
  auto fetch = [&](const BrickKey& k, bool must) -> Decoded {
    CacheKey ck{int(c), k};
    std::shared_future<Decoded> future;
    std::promise<Decoded> promise;
    bool decode = false;
    {
      std::lock_guard<std::mutex> lock(s.mutex);
      auto it = s.map.find(ck);
      if (it != s.map.end()) {
        s.lru.splice(s.lru.begin(), s.lru, it->second.lru);
        future = it->second.future;
      } else {
        future = promise.get_future().share();
        s.lru.push_front(ck);
        s.map.emplace(ck, Impl::Entry{future, s.lru.begin(), 0});
        ++s.decoded;
        decode = true;
      }
    }
    if (decode) {
      Region r = brick_region(source_, k.level, k.brick);
      try {
        auto data = std::make_shared<std::vector<std::uint8_t>>(std::size_t(r.voxels()) * bpv);
        source_.read_region(c, k.level, r, data->data());
        promise.set_value(data);
        std::lock_guard<std::mutex> lock(s.mutex);
        auto it = s.map.find(ck);
        if (it != s.map.end()) {
          it->second.bytes = std::int64_t(data->size());
          s.bytes += it->second.bytes;
        }
        // Evict least recently used, finished entries beyond the capacity (never this one).
        while (s.bytes > s.capacity && s.lru.size() > 1) {
          const CacheKey victim = s.lru.back();
          if (victim == ck) break;
          auto v = s.map.find(victim);
          s.bytes -= v->second.bytes;
          s.lru.pop_back();
          s.map.erase(v);
        }
      } catch (...) {
        promise.set_exception(std::current_exception());
        std::lock_guard<std::mutex> lock(s.mutex);
        auto it = s.map.find(ck);
        if (it != s.map.end()) {  // forget failures: a later read retries and reports again
          s.lru.erase(it->second.lru);
          s.map.erase(it);
        }
      }
    }
    try {
      return future.get();
    } catch (const FormatError&) {
      if (must) throw;
      return nullptr;
    }
  };
  for (int dz = -1; dz <= 1; ++dz)
    for (int dy = -1; dy <= 1; ++dy)
      for (int dx = -1; dx <= 1; ++dx) {
        BrickKey k{key.level, {key.brick[0] + dx, key.brick[1] + dy, key.brick[2] + dz}};
        bool inside = true;
        for (int a = 0; a < 3; ++a)
          if (k.brick[a] < 0 || k.brick[a] >= grid[a]) inside = false;
        // Neighbours are only needed when the border reaches into them.
        if (!inside || (border_ == 0 && (dx || dy || dz))) continue;
        slots[(dz + 1) * 9 + (dy + 1) * 3 + (dx + 1)] = fetch(k, dx == 0 && dy == 0 && dz == 0);
      }

  BorderedBrick out;
  // Per axis: for each output index, the neighbour slot (0..2) and the local coordinate.
  std::vector<int> slot[3];
  std::vector<std::int64_t> local[3], size_of_slot[3];
  for (int a = 0; a < 3; ++a) {
    out.offset[a] = centre.offset[a] - border_;
    out.dims[a] = centre.size[a] + 2 * border_;
    for (std::int64_t i = 0; i < out.dims[a]; ++i) {
      std::int64_t v = std::clamp<std::int64_t>(out.offset[a] + i, 0, g.dims[a] - 1);
      std::int64_t b = v / e;
      slot[a].push_back(int(b - key.brick[a] + 1));
      local[a].push_back(v - b * e);
    }
    for (int k = 0; k < 3; ++k) {
      std::int64_t b = key.brick[a] + k - 1;
      size_of_slot[a].push_back(b < 0 ? 0
                                      : std::min(e, std::max<std::int64_t>(g.dims[a] - b * e, 0)));
    }
  }
  out.data.assign(std::size_t(out.dims[0] * out.dims[1] * out.dims[2]) * bpv, 0);
  std::uint8_t* dst = out.data.data();
  for (std::int64_t z = 0; z < out.dims[2]; ++z)
    for (std::int64_t y = 0; y < out.dims[1]; ++y)
      for (std::int64_t x = 0; x < out.dims[0]; ++x, dst += bpv) {
        const int sx = slot[0][std::size_t(x)], sy = slot[1][std::size_t(y)],
                  sz = slot[2][std::size_t(z)];
        const Decoded& d = slots[sz * 9 + sy * 3 + sx];
        if (!d) continue;
        const std::int64_t nx = size_of_slot[0][std::size_t(sx)],
                           ny = size_of_slot[1][std::size_t(sy)];
        const std::int64_t i = local[0][std::size_t(x)] +
                               nx * (local[1][std::size_t(y)] + ny * local[2][std::size_t(z)]);
        std::memcpy(dst, d->data() + std::size_t(i) * bpv, bpv);
      }
  return out;
}

}  // namespace vispack::render

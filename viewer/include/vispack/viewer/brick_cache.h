// The GPU brick cache (docs/BENCHMARKS.md, 'Viewer: bricks paged by view'): one 3-D texture per
// brick and channel, each with a border of kBorder voxels from its neighbours
// (render/brick_reader.h), within a byte budget
// (--max-gpu-mb). Bricks are decoded on worker threads, in the order requested (the plan's
// `missing` list: coarsest first, then nearest), and uploaded on the GL thread by pump().
// When a new brick does not fit, the least recently used bricks that the current frame does not
// draw are evicted.
//
// Texture formats as VolumeTextures (volume_textures.h): rgba → GL_RGBA8 premultiplied,
// ct → GL_R16_SNORM, labels → GL_R16UI. A channel a brick lacks reads a 1×1×1 zero texture.
// A brick whose stored data is corrupt is uploaded as zeros (shown as missing) and reported.
//
// All members must be called on the thread whose GL context is current. The source must
// outlive the cache.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "vispack/render/brick_tree.h"
#include "vispack/render/volume.h"
#include "vispack/viewer/gl_objects.h"

namespace vispack::viewer {

struct BrickCacheStats {
  std::int64_t uploaded_bricks = 0;  // brick channels uploaded since the last reset_counters()
  std::int64_t uploaded_bytes = 0;
  std::int64_t resident_bytes = 0;  // texture bytes held now
  std::int64_t resident_bricks = 0;
  std::int64_t evicted = 0;
  std::int64_t decoded = 0;  // stored bricks decoded (cache misses of the decoded-brick cache)
  std::int64_t bad_bricks = 0;
  std::vector<std::string> bad_brick_errors;
};

class BrickCache {
 public:
  static constexpr int kBorder = 2;

  // `budget_bytes` bounds the texture bytes held; `threads` decode (0 = resolve_threads()).
  BrickCache(const render::VolumeSource& source, std::int64_t budget_bytes, int threads = 0);
  ~BrickCache();
  BrickCache(const BrickCache&) = delete;
  BrickCache& operator=(const BrickCache&) = delete;

  // Replaces the queue of work: every channel of `channels` of each key that is not resident
  // (nor already being decoded), in this order.
  void request(const std::vector<render::BrickKey>& keys, unsigned channels);
  // Uploads decoded bricks until `budget_seconds` have passed, or with a negative budget until
  // everything requested is resident. Returns the number of brick channels uploaded. Rethrows a
  // worker's unexpected error.
  int pump(double budget_seconds);
  // True while requested work is queued, decoding or waiting for upload.
  bool busy() const;
  bool resident(const render::BrickKey& key, unsigned channels) const;
  // Marks the bricks the current frame draws: they are not evicted until the next call.
  void use(const std::vector<render::BrickKey>& keys);

  struct Brick {
    GLuint texture[render::kChannelCount] = {0, 0, 0};  // 0: the channel is not resident
    std::array<std::int64_t, 3> offset{0, 0, 0};        // level voxel of texel (0, 0, 0)
    std::array<std::int64_t, 3> dims{0, 0, 0};          // texels
    render::CellGrid cells;  // value ranges of its cells (channels: cells.channels)
  };
  // Null when no channel of the brick is resident.
  const Brick* find(const render::BrickKey& key) const;
  // The 1×1×1 zero texture of a channel (for channels a frame does not read).
  GLuint zero_texture(render::Channel c) const;

  const BrickCacheStats& stats() const;
  void reset_counters();  // zeroes uploaded_* (per-frame accounting)
  std::int64_t budget_bytes() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vispack::viewer

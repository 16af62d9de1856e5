// Reads single bricks of a VolumeSource with a border of voxels around them, the unit the GL
// brick cache uploads (one texture per brick and channel). Border voxels come from the
// neighbouring bricks, so trilinear filtering and central-difference gradients inside a brick's
// box see the same voxels as a whole-level texture: no seams. At the level's edges voxel
// indices are clamped (replicated), as GL_CLAMP_TO_EDGE does for a whole-level texture.
//
// Every stored brick is decoded once while it stays in an LRU cache of decoded bricks
// (`cache_bytes`), so reading the 27 bricks around each brick does not decode 27 times.
//
// Thread-safety: read() may be called from several threads at once (a brick being decoded by
// one thread is waited for, not decoded again). The source must outlive the reader.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include "vispack/render/brick_tree.h"
#include "vispack/render/volume.h"

namespace vispack::render {

struct BorderedBrick {
  std::array<std::int64_t, 3> offset{0, 0, 0};  // level voxel of element (0, 0, 0) (may be < 0)
  std::array<std::int64_t, 3> dims{0, 0, 0};    // brick size + 2·border per axis
  std::vector<std::uint8_t> data;               // dims product · channel_bytes(c), x fastest
};

class BorderedBrickReader {
 public:
  BorderedBrickReader(const VolumeSource& source, int border, std::int64_t cache_bytes);
  ~BorderedBrickReader();
  BorderedBrickReader(const BorderedBrickReader&) = delete;
  BorderedBrickReader& operator=(const BorderedBrickReader&) = delete;

  int border() const { return border_; }
  // Throws FormatError (naming the file and brick) when the brick itself does not decode; a
  // neighbour that does not decode contributes zeros to the border.
  BorderedBrick read(Channel c, const BrickKey& key) const;
  // Stored bricks decoded so far (cache misses), for tests and statistics.
  std::int64_t decoded() const;

 private:
  struct Impl;
  const VolumeSource& source_;
  int border_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vispack::render

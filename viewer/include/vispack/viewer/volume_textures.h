// The volume on the GPU: one 3-D texture per channel of one level, uploaded brick by brick.
//
// Texture formats: rgba → GL_RGBA8 holding premultiplied colour (premultiply_rgba8, so linear
// filtering interpolates associated colour); ct → GL_R16_SNORM (HU = value·32767, linear
// filtering); labels → GL_R16UI (nearest, read with texelFetch). A missing channel is a 1×1×1
// texture of zeros.
//
// Upload: bricks of the source's brick edge are read (decoded) on worker threads into a
// bounded queue (at most 2 × threads bricks in flight) and copied with glTexSubImage3D on the
// GL thread, so host memory never holds more than those bricks: never a second full copy.
// All members must be called on the thread whose GL context is current.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "vispack/render/volume.h"
#include "vispack/viewer/gl_objects.h"

namespace vispack::viewer {

struct UploadStats {
  std::int64_t bricks = 0;
  std::int64_t bytes = 0;  // texel bytes sent to GL
  double seconds = 0;      // wall time from begin() to the last brick
  // Bricks whose stored data failed its checksum or did not decode (FormatError from the
  // source): uploaded as zeros (transparent, HU 0, label 0), i.e. shown as missing. One message
  // per bad brick, naming the file and brick (docs/RELIABILITY.md).
  std::int64_t bad_bricks = 0;
  std::vector<std::string> bad_brick_errors;
};

// The finest level of `source` whose dims all fit `max_texture_size` and whose texture bytes
// (4 + 2 + 2 per voxel for the present channels) fit `max_bytes`; the coarsest level if none.
int choose_level(const render::VolumeSource& source, int max_texture_size, std::int64_t max_bytes);
// Texture bytes of a level (present channels only).
std::int64_t level_texture_bytes(const render::VolumeSource& source, int level);

class VolumeTextures {
 public:
  VolumeTextures();  // 1×1×1 zero textures
  ~VolumeTextures();
  VolumeTextures(VolumeTextures&&) noexcept;
  VolumeTextures& operator=(VolumeTextures&&) noexcept;

  // Allocates the textures of `level` and starts the worker threads (0 = resolve_threads()).
  // The `source` must outlive the upload. Throws vispack::Error on a GL error.
  void begin(const render::VolumeSource& source, int level, int threads = 0);
  // Uploads ready bricks until the queue is drained for good or `budget_seconds` has passed
  // (< 0: until done). Returns true when every brick is on the GPU. Rethrows the first error
  // of a worker (FormatError naming the file and brick).
  bool pump(double budget_seconds = -1.0);
  // begin() + pump() until done.
  UploadStats upload(const render::VolumeSource& source, int level, int threads = 0);
  bool complete() const;
  const UploadStats& stats() const;

  const render::LevelGeometry& geometry() const;
  int level() const;
  GLuint texture(render::Channel c) const;
  // True when the channel came from the source (false: the 1×1×1 zero texture).
  bool has(render::Channel c) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vispack::viewer

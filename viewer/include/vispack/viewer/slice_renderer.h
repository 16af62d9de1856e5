// The view-aligned slice renderer (DESIGN.md §4): proxy polygons from slicing.h on a lattice
// fixed in world space, drawn back to front into an RGBA32F accumulation framebuffer with
// premultiplied blending (GL_ONE, GL_ONE_MINUS_SRC_ALPHA; MAX for mip, ADD for average), then
// resolved over the background by a full-screen pass. The formulas are those of
// render/transfer.h and render/reference.h, sample for sample: per fragment the ray segment a
// slice stands for is Δ_ray = Δ / dot(ray, forward), and opacity is corrected with
// Δ_ray / Δ0.
//
// All members must be called on the thread whose GL context is current.
#pragma once

#include <memory>

#include "vispack/render/camera.h"
#include "vispack/render/image.h"
#include "vispack/render/transfer.h"
#include "vispack/viewer/volume_textures.h"

namespace vispack::viewer {

struct FrameInfo {
  std::int64_t slices = 0;  // proxy polygons drawn
  std::int64_t triangles = 0;
  double slice_spacing_mm = 0;  // Δ
};

class SliceRenderer {
 public:
  // Compiles the shaders. Throws vispack::Error (with the driver log) on failure.
  SliceRenderer();
  ~SliceRenderer();
  SliceRenderer(const SliceRenderer&) = delete;
  SliceRenderer& operator=(const SliceRenderer&) = delete;

  // Renders into the accumulation buffer (camera.width × camera.height). Non-finite or empty
  // geometry draws nothing (the frame is the background).
  FrameInfo render(const VolumeTextures& volume, const render::Camera& camera,
                   const render::RenderParams& params);
  // Resolves the accumulation buffer into framebuffer `target` (0 = the window) over the
  // viewport (x, y, w, h), scaling when sizes differ.
  void resolve(GLuint target, int x, int y, int width, int height);
  // Resolves into an internal RGBA8 target of the frame's size and reads it (row 0 at top).
  render::Image8 read_rgba8();
  // The raw accumulation buffer (premultiplied RGBA, or (max, hit) for mip, (Σ HU·Δ, ΣΔ) for
  // average), row 0 at the top.
  render::ImageF read_accumulation();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vispack::viewer

// The view-aligned slice renderer (docs/GOALS.md §4): proxy polygons from slicing.h on a lattice
// fixed in world space, clipped to each piece (a whole level, or the bricks and sub-brick cells
// of the brick cache, in visibility order), accumulated in an RGBA32F framebuffer, then resolved
// over the background by a full-screen pass. Compositing modes (colour, ct, labels, tf2d, iso,
// mpr) draw front to back with associated-colour "under" blending (GL_ONE_MINUS_DST_ALPHA,
// GL_ONE) and early ray termination: every few dozen slices a pass writes depth where the
// accumulated opacity reached 0.999, and the depth test rejects later fragments there before they
// are shaded. Mip (MAX) and average (ADD) draw back to front without termination. One shader
// program per mode (compiled at the mode's first frame). The formulas are those of
// render/transfer.h and render/reference.h, sample for sample: per fragment the ray segment a
// slice stands for is Δ_ray = Δ / dot(ray, forward), and opacity is corrected with
// Δ_ray / Δ0. In the compositing modes that segment is cut to the volume box and to the clip
// plane (the reference integrates exactly inside both): a sample keeps the length of its
// segment's kept part, and moves onto the face or plane that cuts into the segment from the
// eye's side, so cut faces and box faces are sampled where they are (no slice-lattice staircase).
//
// All members must be called on the thread whose GL context is current.
#pragma once

#include <memory>

#include "vispack/render/brick_tree.h"
#include "vispack/render/camera.h"
#include "vispack/render/image.h"
#include "vispack/render/transfer.h"
#include "vispack/viewer/brick_cache.h"
#include "vispack/viewer/volume_textures.h"

namespace vispack::viewer {

struct FrameInfo {
  std::int64_t slices = 0;  // proxy polygons drawn
  std::int64_t triangles = 0;
  double slice_spacing_mm = 0;     // Δ (of the finest piece drawn)
  std::int64_t pieces = 0;         // boxes drawn (1 for a whole level, else bricks or their cells)
  std::int64_t cells_skipped = 0;  // brick cells that cannot contribute (not drawn)
};

// A box of the volume drawn from one set of textures: a whole level, or one brick of the brick
// cache. The slices of the world-fixed lattice of spacing Δ are clipped to `box`; samples read
// the textures at (p − texture_origin_mm)/spacing_mm (texel centres), so a brick texture with a
// border samples exactly like the whole level.
struct VolumePiece {
  GLuint texture[render::kChannelCount] = {0, 0, 0};  // all must be valid texture names
  bool has_rgba = false, has_ct = false;              // the volume has the channel
  render::Vec3 texture_origin_mm{0, 0, 0};            // centre of texel (0, 0, 0), world mm
  render::Vec3 spacing_mm{1, 1, 1};                   // texel spacing (the level's)
  std::array<std::int64_t, 3> texture_dims{1, 1, 1};
  render::Box3 box;               // the part of the volume this piece draws
  double slice_spacing_mm = 1.0;  // Δ of the piece's lattice
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
  // Brick-paged rendering: the bricks of `plan.draw` (back to front) that `cache` holds, each
  // with its own level's Δ; opacities use Δ0 of level 0 (params.reference_length_mm when set),
  // so mixed levels composite into one integral. Bricks not resident are left out.
  FrameInfo render_bricks(const BrickCache& cache, const render::BrickTree& tree,
                          const render::BrickPlan& plan, const render::Camera& camera,
                          const render::RenderParams& params);
  // The general form: pieces in back-to-front visibility order; `volume_box` is the whole
  // volume's box (isosurface rays start where they enter it); `delta0` the opacity length Δ0.
  FrameInfo render_pieces(const std::vector<VolumePiece>& pieces, const render::Camera& camera,
                          const render::RenderParams& params, const render::Box3& volume_box,
                          double delta0);
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

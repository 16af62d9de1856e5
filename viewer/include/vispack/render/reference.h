// The CPU reference ray caster: the same emission–absorption integral, transfer functions and
// sampling as the GL slice renderer (transfer.h), evaluated along each pixel's ray with fine
// steps (midpoint rule, the last partial step weighted by its length). Tests and benchmarks
// compare GL frames against it.
//
// Sampling (identical to the GL textures):
//   colour/CT: trilinear in voxel coordinates v = (x − origin)/spacing, clamped to the outer
//     voxel centres (GL_CLAMP_TO_EDGE); colour is interpolated premultiplied (8-bit texel values
//     round(c·a/255), see premultiply_rgba8), so a transparent neighbour adds no colour (no halo);
//   labels: nearest voxel, never interpolated (labels 1 and 3 never blend into 2).
// Per mode (RenderParams):
//   colour : emission = interpolated premultiplied colour / alpha, opacity = opacity·alpha (or
//            opacity·window01(HU) with OpacitySource::kCt)
//   ct     : emission = ramp(window01(HU)), opacity = opacity·window01(HU)
//   labels : emission = table colour, opacity = table alpha·opacity (·dim_factor when another
//            label is highlighted); ID 0 is transparent
//   mip    : ramp(window01(max HU along the ray));  average: ramp(window01(mean HU))
//   iso    : first crossing of iso_hu, refined by bisection between the two samples around it
//            (refine_iso), Phong-shaded with central-difference gradients (shade_iso)
//   tf2d   : emission and opacity from the 2-D transfer function at (HU, |gradient|)
//   labels : with LabelShading other than flat, the colour follows label_intensity()
//   mpr    : the plane through mpr_target + mpr_offset_mm·forward, normal = forward: the
//            premultiplied colour over the background (or the windowed CT without rgba)
// Result: RGB already composited over the background; alpha = accumulated opacity (1 where a
// mip/average/iso/mpr ray hit something).
#pragma once

#include <cstdint>
#include <vector>

#include "vispack/render/camera.h"
#include "vispack/render/image.h"
#include "vispack/render/transfer.h"
#include "vispack/render/volume.h"

namespace vispack::render {

// 8-bit premultiplication used by both renderers: out = round(c·a/255), alpha unchanged.
void premultiply_rgba8(const std::uint8_t* in, std::uint8_t* out, std::int64_t voxels);

// Samples a VolumeData like the GL textures do. Construction premultiplies a copy of rgba.
class VolumeSampler {
 public:
  explicit VolumeSampler(const VolumeData& data);
  const VolumeData& data() const { return data_; }
  // Continuous voxel coordinates of world point p (mm).
  Vec3 voxel_coords(Vec3 p) const;
  // Trilinear premultiplied colour in [0, 1] (alpha = coverage) at world point p.
  Rgba colour(Vec3 p) const;
  // Trilinear HU at world point p.
  double hu(Vec3 p) const;
  // Central-difference gradient of HU (HU/mm) with one-voxel offsets at world point p.
  Vec3 hu_gradient(Vec3 p) const;
  // Nearest-voxel label at world point p.
  std::uint16_t label(Vec3 p) const;

 private:
  const VolumeData& data_;
  std::vector<std::uint8_t> premultiplied_;
};

// Intensity t ∈ [0, 1] that modulates a segment's colour in labels mode (transfer.h
// LabelShading): the windowed CT when the volume has CT, else the colour's luminance.
double label_intensity(const VolumeSampler& sampler, const RenderParams& params, Vec3 p);

// Isosurface hit between ray parameters ta (value fa < iso) and tb (value fb >= iso):
// kIsoBisectionSteps bisection steps, then linear interpolation inside the last bracket.
double refine_iso(const VolumeSampler& sampler, const Ray& ray, double iso, double ta, double fa,
                  double tb, double fb);

// Emission (straight RGB) and opacity per Δ0 of one sample at world point p, for the
// compositing modes (colour, ct, labels). Shared by the reference and the tests.
Rgba classify(const VolumeSampler& sampler, const RenderParams& params, Vec3 p);

struct ReferenceOptions {
  double steps_per_voxel = 16.0;  // fine step δ = voxel_length_along(forward) / steps_per_voxel
  int threads = 0;                // 0 = resolve_threads()
};

// Renders one frame of `data` (one level) seen by `camera`. Thread-safe (no shared state).
ImageF render_reference(const VolumeData& data, const Camera& camera, const RenderParams& params,
                        const ReferenceOptions& options = {});

// Slice spacing Δ (mm) a renderer uses for this camera and volume:
// voxel_length_along(camera.forward, spacing) / slices_per_voxel (slices_per_voxel clamped to
// [1/64, 1024]).
double slice_spacing(const Camera& camera, const LevelGeometry& geometry, double slices_per_voxel);
// The reference length Δ0 of opacities: the smallest voxel spacing (mm).
double reference_length(const LevelGeometry& geometry);

}  // namespace vispack::render

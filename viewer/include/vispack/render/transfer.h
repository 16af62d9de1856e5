// Render modes, their parameters and the transfer functions. The GL shaders
// (viewer/src/gl/shaders.h) implement exactly these formulas; the CPU reference ray caster
// calls these functions, so a change here must be mirrored there.
//
// Compositing model (seeds 001, 003): emission–absorption with associated (premultiplied)
// colour. A sample's opacity α is defined per reference length Δ0 = the smallest voxel
// spacing (mm); a sample that stands for a ray segment of length Δ gets
//   α' = 1 − (1 − α)^(Δ/Δ0)        (opacity_correct)
// and contributes (α'·c, α'). Opacity is clamped to [0, 1] first (α > 1 and NaN never reach
// pow with a negative base).
//
// CT texture mapping (documented for the GL side): HU are stored in an R16_SNORM texture;
// the shader reads s ∈ [−1, 1] and HU = s·32767 (−32768 reads as −32767).
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "vispack/render/math.h"
#include "vispack/render/volume.h"

namespace vispack::render {

enum class Mode { kColour, kCt, kMip, kAverage, kIso, kLabels, kMpr, kTf2d };
// "colour", "ct", "mip", "average", "iso", "labels", "mpr", "tf2d"
const char* mode_name(Mode m);
// Inverse of mode_name (also accepts "color"); nullopt for an unknown name.
std::optional<Mode> mode_from_name(const std::string& name);

// Where colour mode takes its opacity from: the rgba alpha (body coverage) or the CT window.
enum class OpacitySource { kAlpha, kCt };

struct Rgba {
  float r = 0, g = 0, b = 0, a = 0;
};

// A colour ramp of kRampSize entries sampled linearly: value t ∈ [0, 1] reads position
// t·(kRampSize − 1) (entries at integer positions), as a GL texture of kRampSize texels read at
// (t·(N − 1) + 0.5)/N does.
constexpr int kRampSize = 256;
using ColourRamp = std::array<Rgba, kRampSize>;
// Presets: "grey" (black → white), "bone" (black → red-brown → ivory → white), "hot".
// Unknown names fall back to "grey". Alpha of every entry is 1 (opacity comes from the window).
ColourRamp make_ramp(const std::string& name);
Rgba sample_ramp(const ColourRamp& ramp, double t);

// Label colour table: RGBA per ID (alpha = opacity per Δ0); 0 is transparent.
// Covers IDs 0..65535 (a 256×256 texture on the GL side, texel (id & 255, id >> 8)).
constexpr int kLabelTableSize = 65536;
std::vector<Rgba> make_label_colours(const std::vector<Label>& labels, double opacity);

// Labels mode colouring (seed 004): flat table colour; the table colour modulated by the
// intensity t (colour·(k + (1 − k)·t), k = kModulatedFloor = 0.5: "fade each segment towards
// black", but never below k of its colour, so a segment of low intensity stays readable); or a ramp
// per segment (black at t = 0, the segment colour at t = 0.5, white at t = 1). t = window01(HU)
// when the volume has CT, else the luminance (0.299, 0.587, 0.114) of the straight colour (0 where
// alpha is 0).
enum class LabelShading { kFlat, kModulated, kRamp };
constexpr double kModulatedFloor = 0.5;
const char* label_shading_name(LabelShading s);  // "flat", "modulated", "ramp"
std::optional<LabelShading> label_shading_from_name(const std::string& name);
// Colour of a segment of table colour `c` at intensity t ∈ [0, 1] (alpha unchanged).
Rgba shade_label(const Rgba& c, LabelShading shading, double t);

// A 2-D transfer function over (CT value, gradient magnitude) (seed 003): a table of
// kValues × kGradients RGBA entries (value fastest; alpha = opacity per Δ0), the value axis
// spanning [value_min, value_max] HU and the gradient axis [0, gradient_max] HU/mm. Entry (i, j)
// sits at value t = i/(kValues − 1) and gradient u = j/(kGradients − 1); lookups are bilinear
// and clamp to the edges (as a GL texture read at cell centres). Gradients are central
// differences with one-voxel offsets (VolumeSampler::hu_gradient).
struct TransferFunction2D {
  static constexpr int kValues = 128;
  static constexpr int kGradients = 64;
  double value_min = -1000.0, value_max = 2000.0, gradient_max = 400.0;
  std::vector<Rgba> table = std::vector<Rgba>(std::size_t(kValues) * kGradients);
  Rgba sample(double hu, double gradient_magnitude) const;
  // True when some entry a lookup of a value in [hu_lo, hu_hi] (any gradient) may read has
  // alpha > 0 (empty-space skipping).
  bool any_opacity(double hu_lo, double hu_hi) const;
};
// One editor widget: a box in (value, gradient) space, opacity a tent over the value range
// (peak at its centre) and, over the gradient range, flat or (gradient_weighted) rising linearly
// from 0 at gradient_lo to the peak at gradient_hi, so that boundaries (high gradient magnitude)
// show and the insides of tissues (low gradient) stay clear; the table is the maximum (by
// alpha) of all widgets.
struct Tf2dWidget {
  double value_lo = 200, value_hi = 1400;     // HU
  double gradient_lo = 0, gradient_hi = 400;  // HU/mm
  Rgba colour{0.95f, 0.9f, 0.8f, 0.6f};       // alpha = peak opacity per Δ0
  bool gradient_weighted = false;
};
TransferFunction2D make_tf2d(const std::vector<Tf2dWidget>& widgets, double value_min = -1000,
                             double value_max = 2000, double gradient_max = 400);

// Isosurface refinement: the hit is bracketed by the two samples around the crossing, refined
// by this many bisection steps, then interpolated linearly inside the last bracket.
constexpr int kIsoBisectionSteps = 6;

struct RenderParams {
  Mode mode = Mode::kColour;
  double slices_per_voxel = 2.0;  // Δ = voxel_length_along(view dir) / slices_per_voxel
  double opacity = 1.0;           // multiplies every opacity (per Δ0) before correction
  OpacitySource opacity_source = OpacitySource::kAlpha;
  double window_center_hu = 300.0;  // CT window (ct, mip, average, colour with CT opacity)
  double window_width_hu = 1500.0;
  ColourRamp ramp = make_ramp("bone");
  double iso_hu = 300.0;  // isosurface threshold
  Rgba iso_colour{0.92f, 0.86f, 0.75f, 1.0f};
  int highlight_label = -1;  // labels mode: this ID at full opacity, the others dimmed
  double dim_factor = 0.2;   // opacity factor of the labels that are not highlighted
  LabelShading label_shading = LabelShading::kFlat;
  TransferFunction2D tf2d = make_tf2d({Tf2dWidget{}});  // tf2d mode
  std::vector<Rgba> label_colours;  // kLabelTableSize entries (make_label_colours)
  Rgba background{0, 0, 0, 1};      // composited behind the volume (alpha ignored)
  bool jitter = false;              // offset samples per pixel by up to ±Δ/2 (hash of pixel)
  double mpr_offset_mm = 0.0;       // mpr: plane through target + offset·forward
  Vec3 mpr_target{0, 0, 0};         // mpr: usually the orbit target (box centre)
  // Optional clip plane: samples with dot(clip_normal, x) > clip_d are removed.
  bool clip = false;
  Vec3 clip_normal{1, 0, 0};
  double clip_d = 0.0;
  // Δ0 of the opacities (mm); <= 0: the smallest spacing of the level rendered. The brick-paged
  // renderer draws several levels at once and sets it to level 0's (reference_length()).
  double reference_length_mm = 0.0;
};

// α' = 1 − (1 − α)^ratio with α clamped to [0, 1] (NaN → 0) and ratio >= 0 (NaN → 1).
double opacity_correct(double alpha, double ratio);

// Window → [0, 1]: (hu − (center − width/2)) / width, clamped; width <= 0 acts as a step.
double window01(double hu, double center, double width);

// Phong shading of the isosurface (headlight: light and eye along −ray_dir).
// `gradient` in HU/mm; a zero or non-finite gradient shades as a surface facing the viewer
// (never NaN). Returns an opaque colour in [0, 1].
Rgba shade_iso(const Rgba& colour, Vec3 gradient, Vec3 ray_dir);

// Front-to-back "under" compositing of one associated-colour sample: acc += (1 − acc.a)·s.
inline void composite_under(Rgba& acc, const Rgba& s) {
  float t = 1.0f - acc.a;
  acc.r += t * s.r;
  acc.g += t * s.g;
  acc.b += t * s.b;
  acc.a += t * s.a;
}
// Back-to-front "over" compositing (what GL blending ONE, ONE_MINUS_SRC_ALPHA does).
inline void composite_over(Rgba& acc, const Rgba& s) {
  float t = 1.0f - s.a;
  acc.r = s.r + t * acc.r;
  acc.g = s.g + t * acc.g;
  acc.b = s.b + t * acc.b;
  acc.a = s.a + t * acc.a;
}

}  // namespace vispack::render

// A Visible-Human-style slice folder synthesised from a REAL CT volume (the head-CT case of
// docs/ARCHITECTURE.md "The phantom folder"), with its own ground truth.
//
// Unlike the analytic presets (phantom.h), the anatomy here is whatever the CT holds: it changes
// from slice to slice as a real body does, there are no fiducial tubes, the CT is drift-free and
// `scale`× coarser than the colour, and the CT shows things the photographs do not (the head
// holder). Everything is defined from ONE continuous model so the truth and the slices agree by
// construction.
//
// Grids and frames (docs/ARCHITECTURE.md "Slice transforms", docs/ARCHITECTURE.md "The output
// frame"):
//   CT grid:      Wct × Hct pixels of ct.spacing_mm[0] mm, slice k of the output = CT slice
//                 first + k (written as ct/ct_<k>.png, ct.z_offset_mm 0).
//   output grid:  W = scale·Wct + 2·margin, H = scale·Hct + 2·margin pixels of
//                 ct.spacing_mm[0] / scale mm (the margin, 32·scale by default, is gel around the
//                 CT's field of view: room for the drift; outside the CT the model is air); the
//                 CT's frame at the colour resolution with register.output_frame = identity:
//                 CT pixel u lands on q = c + scale·(u − c_ct), c = ((W−1)/2, (H−1)/2),
//                 c_ct = ((Wct−1)/2, (Hct−1)/2). truth/*.nrrd lie on this grid.
//   colour slice k (observed, W × H, the same size): output point q appears at
//                 p = c + R(θ_k)(q − c) + d_k, with (θ_k, d_k) = a constant camera offset
//                 (|d| 8..12 px·scale/2, |θ| 1..2°) + a slow random walk (σ 0.3 px and 0.05° per
//                 slice) + one block jump at slice N/2 (20..35 px·scale/2, 3..5°), each step
//                 checked against the convex hull of the body over the stack so the body stays
//                 ≥ 2 px inside the frame (a walk step that would leave is reflected, the jump
//                 turned). Slice 0 is therefore NOT the identity. truth/transforms.json has
//                 "frame": "ct", "reference_slice": null.
//
// The continuous model at output point q (real coordinates) of slice k:
//   HU(q)     = the CT slice, bilinear in u = c_ct + (q − c)/scale (edges replicated);
//   body(q)   = HU(q) > kBodyHu (−400 HU) AND one of the 4 output-grid pixels around q belongs to
//               the body component B: the largest 3-D connected set (8-connected in a slice,
//               face-connected between slices) of output-grid voxels with HU > kBodyHu. On the
//               grid itself, body = membership of B. Air cavities (HU ≤ −400) are not body in
//               the colour (gel fills them), and anything separate from the body (the head
//               holder) is not body.
//   truth/mask.nrrd = membership of B with enclosed in-slice cavities filled (background not
//               4-connected to the frame's border counts as body, as a body mask fills holes).
//   depth(q)  = distance (output px) from q to the nearest non-body pixel, bilinear of the
//               slice's Euclidean distance transform of the mask.
//   label(q)  = 0 outside the body; else 1 skin (depth ≤ 2 mm), 4 bone (HU > 250),
//               2 fat (HU ≤ −30), 3 soft tissue (otherwise). (palette.json; seg slices.)
//   colour(q) = tissue colour from HU and depth (skin, fat, muscle → brain with depth, marrow →
//               cortical bone with HU), times a per-slice texture (value noise with a fresh
//               lattice every slice, so texture never repeats between slices); outside the body
//               translucent blue gel, tinted by the tissue within a few pixels (cavities too).
//   The body/gel boundary in colour is hard: every colour pixel shows tissue exactly where body(q)
//   holds at its q and gel elsewhere.
// Observed colour(p) = colour(q(p)) · gain_k · (1 + tilt_k · (p − c)) + N(0, 3²) (8 bit),
// gain_k = 1 ± 6 %, tilt a lighting gradient of up to ±5 % across the frame, both per slice.
// seg(p) = palette[label(q(p))] (exact PNG). truth/seg_labels.nrrd = those IDs per seg pixel.
//
// Deterministic: the same CT, options and seed give a byte-identical folder (own RNG, no
// timestamps, per-slice seeds independent of the thread schedule).
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace vispack::phantom {

inline constexpr double kBodyHu = -400.0;  // the body threshold of the continuous model

// A CT volume in HU, x fastest, then y, then z.
struct CtVolume {
  int width = 0, height = 0, slices = 0;
  std::array<double, 3> spacing_mm{1, 1, 1};  // pixel x, pixel y, slice spacing
  std::vector<std::int16_t> hu;
  std::string source;  // where it was read from (for messages and truth metadata)
  const std::int16_t* slice(int k) const { return hu.data() + std::size_t(width) * height * k; }
};

// Reads a CT volume from
//   - a .nrrd file (3-D scalar, any integer or float type; values are HU; spacing from the file),
//   - a pipeline config file, or a folder holding config.json (e.g. data/samples/head-ct): its
//     `ct` section (slices, slope/intercept, pixel_spacing_mm), slice spacing spacing_mm[2].
// Throws InputError / ConfigError / FormatError naming the path when it is none of these, the
// slices differ in size, or the volume is empty.
CtVolume read_ct_volume(const std::string& path);

struct FromCtOptions {
  std::uint64_t seed = 1;
  int slices = 0;      // 0: every CT slice; else N (2..ct.slices) consecutive CT slices
  int first = -1;      // first CT slice used; -1: the N slices centred in the volume
  int scale = 2;       // colour pixels per CT pixel (1..8)
  int margin_px = -1;  // gel added around the CT's field of view on each side, colour pixels;
                       // -1: 32·scale (so 640×640 from a 256×256 CT at scale 2)
  bool drift = true;   // false: the random walk is exactly zero (camera offset and jump stay)
  bool jump = true;    // one block jump at slice N/2 (needs N >= 4)
  int threads = 0;     // 0 = all cores; output independent of it
  bool quiet = false;  // no progress on stderr
  // The colour at a z spacing ct_every times finer than the CT's (docs/ARCHITECTURE.md, 'Each input
  // at its own z': the VH female's 3:1, the Visible Korean's 5:1): the CT volume is interpolated
  // linearly along z (ct_every − 1 slices between each two) to synthesise the colour slices and the
  // truth, and ct/ keeps only the CT's own slices, every ct_every-th colour slice (written as
  // ct_<k/ct_every>; config ct.slice_spacing_mm = the CT's slice spacing). `slices` and `first`
  // count colour slices; `first` must be a multiple of ct_every (the default, centred, is rounded
  // down to one). 1..10.
  int ct_every = 1;
};

struct FromCtSummary {
  int width = 0, height = 0, slices = 0;  // output / colour grid
  int ct_width = 0, ct_height = 0, first_ct_slice = 0;
  int jump_slice = -1;
  double body_fraction = 0;  // body voxels / all voxels of the output grid
  double seconds = 0;
};

// Writes rgb/, ct/, seg/, palette.json, config.json and truth/ (rgb, ct, mask, labels,
// seg_labels NRRDs on the output grid, transforms.json) under `out_dir` (created if missing).
// Throws UsageError for bad options, IoError when a file cannot be written, Error when the body
// leaves no room in the frame for the drift.
FromCtSummary make_phantom_from_ct(const std::string& out_dir, const CtVolume& ct,
                                   const FromCtOptions& options);

}  // namespace vispack::phantom

// The synthetic Visible-Human-style slice folder with ground truth (DESIGN.md section 5,
// docs/ARCHITECTURE.md "The phantom folder").
//
// A body of nested shapes (skin, fat, muscle, bone, lungs, heart, liver, kidneys, connective
// tissue) whose cross-sections change smoothly with z, in blue translucent gel with two green
// fiducial tubes and a gel-filled notch open to the outside. Every slice is rendered from one
// analytic model (functions of position in mm and slice index), so the truth volumes and the
// drifted slices agree by construction:
//   truth(q)    = model(q)                        on the output grid,
//   observed(p) = gain_k · model(q(p)) + noise    with p = c + R(θ_k)(q − c) + d_k,
//   seg(p)      = palette[label(q(p))]            (nearest, no blending; the IDs themselves are
//                                                  truth/seg_labels.nrrd, on the drifted grid),
//   ct(u)       = ct_model(q(u)) + noise          with q = c + s·R(φ)(u − c_ct) + e (ct_to_rgb).
// The generator is deterministic: the same options give a byte-identical folder on the same
// build (own RNG and distributions, no timestamps, per-slice seeds independent of scheduling).
#pragma once

#include <cstdint>
#include <optional>
#include <string>

namespace vispack::pipeline {

// Geometry of a preset (the output grid is the RGB grid).
struct PhantomPreset {
  std::string name;
  int width = 0, height = 0, slices = 0;  // RGB / output grid, voxels
  double pixel_mm = 0.33;                 // RGB pixel spacing (x and y)
  double slice_mm = 1.0;                  // slice spacing (RGB, CT and output)
  int ct_size = 0;                        // CT matrix is ct_size × ct_size
  double ct_pixel_mm = 0.9;               // CT pixel spacing (larger than pixel_mm)
  bool defects = false;                   // one black and one duplicated slice by default
};

// The presets: tiny 96×64×24, small 256×192×64, medium 512×384×160, vhp 2048×1216×16.
// Throws UsageError naming the preset when it is unknown.
PhantomPreset phantom_preset(const std::string& name);

struct PhantomOptions {
  std::string preset = "small";
  std::uint64_t seed = 1;
  int slices = 0;               // 0: the preset's default; otherwise 2..100000
  bool rgb_raw = false;         // planar 8-bit header-less .raw RGB (NLM style) instead of PNG
  bool seg_jpeg = false;        // JPEG (quality 90) segmentation instead of exact PNG
  std::optional<bool> defects;  // black + duplicated slice; nullopt = the preset's default
  int threads = 0;              // 0 = all cores (parallel over slices; output independent of it)
  bool quiet = false;           // no progress lines on stderr
};

struct PhantomSummary {
  int width = 0, height = 0, slices = 0;
  int ct_size = 0;
  int jump_slice = -1;       // index of the slice where the block jump happens
  int black_slice = -1;      // -1 when defects are off
  int duplicate_slice = -1;  // an exact copy of slice duplicate_slice − 1; -1 when off
  double seconds = 0.0;      // wall time of the generation
};

// Writes the phantom folder under `out_dir` (created if missing): rgb/, ct/, seg/, palette.json,
// config.json and truth/ as docs/ARCHITECTURE.md describes. Every file is written atomically;
// files of an earlier run in rgb/, ct/ and seg/ that match the phantom's own name patterns but
// are not part of this run are removed, so the folder always holds exactly one phantom.
// Throws UsageError for bad options (unknown preset, slice count out of range, defects with
// fewer than 6 slices), IoError when a file cannot be written.
PhantomSummary make_phantom(const std::string& out_dir, const PhantomOptions& options);

}  // namespace vispack::pipeline

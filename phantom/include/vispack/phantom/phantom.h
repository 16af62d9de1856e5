// The synthetic Visible-Human-style slice folder with ground truth (docs/GOALS.md §5,
// docs/ARCHITECTURE.md "The phantom folder").
//
// A body of nested shapes (skin, fat, muscle, bone, lungs, heart, liver, kidneys, connective
// tissue) whose cross-sections change with z, in blue translucent gel with (by default) two green
// fiducial tubes and a gel-filled notch open to the outside. Every slice is rendered from one
// analytic model (functions of position in mm and slice index), so the truth volumes and the
// drifted slices agree by construction:
//   truth(q)    = model(q)                        on the output grid,
//   observed(p) = gain_k · model(q(p)) + noise    with p = c + R(θ_k)(q − c) + d_k,
//   seg(p)      = palette[label(q(p))]            (nearest, no blending; the IDs themselves are
//                                                  truth/seg_labels.nrrd, on the drifted grid),
//   ct(u)       = ct_model(q(u)) + noise          with q = c + s·R(φ)(u − c_ct) + e (ct_to_rgb).
// The output grid is the CT's frame at the colour resolution (docs/ARCHITECTURE.md "The output
// frame"): (φ, e) is register.output_frame (identity), s = CT pixel / colour pixel, and every T_k =
// (θ_k, d_k) is a constant colour-camera offset against the CT plus the drift, so slice 0 is not
// the identity; truth/transforms.json says "frame": "ct", "reference_slice": null. That file is
// written by the phantom's own writer, independent of the pipeline's ON PURPOSE (a bug in the
// pipeline's writer must not hide in the truth); config.json goes through the pipeline's
// write_config. Units: x, y in output pixels (pixel_mm each), z in slices (slice_mm); angles in
// degrees. The generator is deterministic: the same options give a byte-identical folder on the
// same build (own RNG and distributions, no timestamps, per-slice seeds independent of scheduling).
// Thread-safety: make_phantom may run concurrently on different output folders.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace vispack::phantom {

// Geometry of a preset (the output grid is the RGB grid).
struct PhantomPreset {
  std::string name;
  int width = 0, height = 0, slices = 0;  // RGB / output grid, voxels
  double pixel_mm = 0.33;                 // RGB pixel spacing (x and y)
  double slice_mm = 1.0;                  // slice spacing (RGB, CT and output)
  int ct_size = 0;                        // CT matrix is ct_size × ct_size
  double ct_pixel_mm = 0.9;               // CT pixel spacing (larger than pixel_mm)
  bool defects = false;                   // one black and one duplicated slice by default
  bool fiducials = true;                  // the two fiducial tubes by default
  bool varying_anatomy = false;           // anatomy moves, grows, vanishes and tapers along z
  bool limbs = false;                     // a whole body: head, arms, legs, feet, toes, table
};

// The presets: tiny 96×64×24, small 256×192×64, medium 512×384×160, vhp 2048×1216×16 (the
// classic body: slow, smooth changes along z, fiducial tubes in every slice); anatomy
// 256×192×96 and anatomy-vhp 2048×1216×16 (no fiducials, CT 2× coarser, and an anatomy that
// does not flatter registration: the outline's centre moves steadily by 0.3 × 0.12 of H/2 over
// the stack, the body tapers to nothing at both ends (size ∝ sin(π t)^0.3), organs wander,
// grow and vanish, and the texture is drawn afresh for every slice); male 2048×1216×200 (CT
// 512², 1.4 mm), korean 4368×2912×64 (the Visible Korean's colour slice, 0.1 mm; CT 481², 1 mm)
// and male-small 384×228×64 (CT 1.5× coarser): a whole body from head to toes
// (docs/ARCHITECTURE.md, 'The body mask: every part is body'), several parts in most slices: the
// head tapering from nothing, arms beside the torso (gaps 2–40 px at 1216 px height, the right arm
// resting on the table in part of the stack), the pelvis parting into two legs of the same size,
// two feet, five toes per foot tapering to nothing; a table in the CT touching the torso and the
// arm in some slices; no fiducials; anatomy as varying as `anatomy`'s. Throws UsageError naming the
// preset when it is unknown.
PhantomPreset phantom_preset(const std::string& name);

struct PhantomOptions {
  std::string preset = "small";
  std::uint64_t seed = 1;
  int slices = 0;                 // 0: the preset's default; otherwise 2..100000
  bool rgb_raw = false;           // planar 8-bit header-less .raw RGB (NLM style) instead of PNG
  bool seg_jpeg = false;          // JPEG (quality 90) segmentation instead of exact PNG
  std::optional<bool> defects;    // black + duplicated slice; nullopt = the preset's default
  std::optional<bool> fiducials;  // the two fiducial tubes; nullopt = the preset's default
  bool drift = true;              // false: the random walk is exactly zero (camera offset stays)
  bool jump = true;               // false: no block jump
  // How the true drift moves from slice to slice. kWalk: the Gaussian random walk (0.3 px, 0.05°
  // per step) that the registration's prior also assumes. The others break that assumption, so a
  // score shows what the solver does when the drift is not its prior: kHeavy, heavy-tailed steps
  // (Student's t, 2 degrees of freedom, the same scale, capped at 15 σ: rare steps of a few px
  // that are no block jump); kRotation, the walk plus a slow systematic rotation (0.02° per
  // slice); kBowed, the walk plus a bowed stack (x and y follow half a sine over the stack,
  // amplitude 2 % of the frame height, at least 1 px).
  enum class DriftModel { kWalk, kHeavy, kRotation, kBowed };
  DriftModel drift_model = DriftModel::kWalk;
  // Block jump magnitude in px, drawn uniformly in [min, max]; 0, 0 = the preset's (7..9 px on
  // frames under 128 px high, else 10..15 px). 3..6 px jumps lie at or below the default
  // register.jump_px (6): the anchor, not the jump flag, has to catch them.
  double jump_px_min = 0, jump_px_max = 0;
  double ct_scale = 0;  // CT pixel / colour pixel; 0 = the preset's (0.25..16)
  // A CT slice only at every ct_every-th colour slice (k = 0, e, 2e, ...; written as ct_<k/e>),
  // config ct.slice_spacing_mm = e · slice spacing (docs/ARCHITECTURE.md, 'Each input at its own
  // z': the VH female's 3:1, the Visible Korean's 5:1). Colour slices beyond the last CT slice lie
  // outside the CT's z range.
  int ct_every = 1;  // 1..1000
  // The same for the segmentation (written as seg_<k/e>, config seg.slice_spacing_mm).
  int seg_every = 1;   // 1..1000
  int threads = 0;     // 0 = all cores (parallel over slices; output independent of it)
  bool quiet = false;  // no progress lines on stderr
  // The male's artefacts as NLM ships it (docs/ARCHITECTURE.md, 'A stack at full length'):
  // `blocks` ≥ 2 cuts the stack into that many blocks of equal length with a block jump at each
  // of the blocks − 1 boundaries (instead of the one jump at N/2) and a brightness step per block
  // (block gain 1 ± 8 %, times the per-slice gain); `black_slices` black slices spread over the
  // stack, never slice 0 nor a jump. 0 and 0: one jump at N/2, no step, as before.
  int blocks = 0;        // 0 or 2..64, at most slices / 4
  int black_slices = 0;  // 0..slices / 4
  // 0 or 1: the truth volumes of the whole stack (truth/*.nrrd, 10 bytes a voxel, built in memory:
  // at most 12 GB). K ≥ 2, a streamed folder for stacks at full length: no truth volume is
  // held; truth/sample/mask_NNNN.png (0/255) and labels_NNNN.png (16-bit IDs) are written for
  // every K-th slice (0, K, 2K, ...) and truth/transforms.json lists them ("truth_sample");
  // vispack-score scores the masks and labels on those slices (score.h).
  int truth_every = 0;
  // Bytes the file system must keep free after the folder is written: make_phantom estimates the
  // bytes it will write, checks std::filesystem::space first and throws before writing anything
  // when they do not fit (the message names the folder, the bytes needed and the bytes free).
  std::uint64_t keep_free_bytes = 0;
};

struct PhantomSummary {
  int width = 0, height = 0, slices = 0;
  int ct_size = 0;
  int jump_slice = -1;                // index of the slice where the block jump happens
  int black_slice = -1;               // -1 when defects are off
  int duplicate_slice = -1;           // an exact copy of slice duplicate_slice − 1; -1 when off
  std::vector<int> jump_slices;       // every block jump (jump_slice is the first; empty: none)
  std::vector<int> black_slices;      // every black slice (black_slice is the first)
  std::vector<int> truth_sample;      // truth_every ≥ 2: the slices of truth/sample/
  std::uint64_t estimated_bytes = 0;  // what the free-space check counted
  double seconds = 0.0;               // wall time of the generation
};

// Writes the phantom folder under `out_dir` (created if missing): rgb/, ct/, seg/, palette.json,
// config.json and truth/ as docs/ARCHITECTURE.md describes. Every file is written atomically;
// files of an earlier run in rgb/, ct/ and seg/ that match the phantom's own name patterns but
// are not part of this run are removed, so the folder always holds exactly one phantom.
// Throws UsageError for bad options (unknown preset, slice count out of range, defects with
// fewer than 6 slices, blocks or black slices that do not fit), IoError when a file cannot be
// written or the file system lacks the space (keep_free_bytes), before the first slice.
PhantomSummary make_phantom(const std::string& out_dir, const PhantomOptions& options);

// "walk" | "heavy" | "rotation" | "bowed" (the command line's --drift); throws UsageError naming
// the word otherwise.
PhantomOptions::DriftModel parse_drift_model(const std::string& name);

}  // namespace vispack::phantom

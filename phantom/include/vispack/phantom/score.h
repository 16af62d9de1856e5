// Scoring pipeline outputs against a phantom's truth: one function per measure, used by the
// tests, the benchmarks and vispack-score.
//
// Inputs: the truth folder (truth/transforms.json, mask.nrrd, labels.nrrd of a phantom folder)
// and a pipeline work folder (docs/ARCHITECTURE.md "Work folder layout": register/transforms.json,
// mask/mask_NNNN.png, labels/labels_NNNN.png, NNNN = the stack index, at least 4 digits). Both
// transforms files are read by this module's own reader (not the pipeline's), so a bug in the
// pipeline's reader or writer cannot cancel out.
//
// Transform convention (docs/ARCHITECTURE.md "Slice transforms"): a point q of the W×H output
// grid appears in observed slice k at T_k(q) = c + R(θ_k)(q − c) + d_k, c = ((W−1)/2, (H−1)/2).
// All functions are pure and thread-safe; errors throw vispack::Error subclasses naming the file.
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "vispack/common/nrrd.h"

namespace vispack::phantom {

struct SliceRigid {
  double rotation_deg = 0, dx_px = 0, dy_px = 0;
};

// The largest displacement (output pixels) between a(q) and b(q) over the 4 corners
// (0,0), (W−1,0), (0,H−1), (W−1,H−1) and the centre c of a W×H grid.
double transform_error_px(const SliceRigid& a, const SliceRigid& b, int width, int height);

// The transform of slice k relative to slice r, T_k ∘ T_r⁻¹, as a rigid transform about the same
// centre: rotation θ_k − θ_r, shift d_k − R(θ_k − θ_r) d_r.
SliceRigid relative_to(const SliceRigid& t_k, const SliceRigid& t_r, int width, int height);

// A transforms.json (truth or estimate) as this module reads it.
struct TransformsFile {
  int width = 0, height = 0;
  std::string frame;  // "ct", "slice0", "fiducials", or "" when the file has no "frame"
  struct Slice {
    SliceRigid t;
    bool jump = false, black = false;
    int duplicate_of = -1;
  };
  std::vector<Slice> slices;
  // A streamed phantom's truth (phantom.h truth_every): the slices whose mask and labels truth
  // lie in truth/sample/ ("truth_sample"); empty when the file has none.
  std::vector<int> truth_sample;
};
// Throws IoError (unreadable) or FormatError naming the file and key.
TransformsFile read_transforms_file(const std::string& path);

struct DriftScore {
  std::vector<double> error_px;  // per slice; NaN where not scored (lost = black, or duplicated,
                                 // in the truth: the picture shows no slice k to register)
  double rms_px = 0, max_px = 0;
  int max_slice = -1, scored = 0;
  // The same after expressing both stacks relative to their slice 0 (T_k ∘ T_0⁻¹): what is left
  // when the absolute placement (the frame) is ignored; a diagnostic, not the goal.
  double relative_rms_px = 0, relative_max_px = 0;
  // Over the scored slices whose truth body covers ≥ 1 % of the frame (score_work only: where the
  // slice itself shows something to register; NaN when not computed).
  double body_rms_px = std::numeric_limits<double>::quiet_NaN();
  double body_max_px = std::numeric_limits<double>::quiet_NaN();
  int body_slices = 0;
  // Drift where it shows (score_work only): per slice the largest displacement between
  // estimate and truth over the truth body's pixels (its convex hull's vertices), NaN where the
  // truth slice has no body or is not scored. The output clears everything outside the body, so
  // this is a slice's visible error; the frame's corners (error_px) also count a rotation that a
  // small body cannot show and that does no harm. RMS and max over the slices with body.
  std::vector<double> over_body_px;
  double over_body_rms_px = std::numeric_limits<double>::quiet_NaN();
  double over_body_max_px = std::numeric_limits<double>::quiet_NaN();
  int over_body_max_slice = -1, over_body_slices = 0;
};
// The largest displacement (output pixels) between a(q) and b(q) over `points` (output-grid
// pixels) of a W×H grid; 0 when `points` is empty.
double transform_error_over_px(const SliceRigid& a, const SliceRigid& b, int width, int height,
                               const std::vector<cv::Point>& points);
// Per-slice cumulative drift error = transform_error_px(estimate_k, truth_k). Throws Error when
// the two files differ in grid size or slice count.
DriftScore score_drift(const TransformsFile& truth, const TransformsFile& estimate);

struct JumpScore {
  int true_jumps = 0, found = 0, missed = 0, false_jumps = 0;
  std::vector<int> missed_slices, false_slices;
};
// A true jump at k is found when the estimate flags k; any other flagged slice is false.
JumpScore score_jumps(const TransformsFile& truth, const TransformsFile& estimate);

struct MaskScore {
  std::vector<double> iou;  // per slice; NaN where truth and estimate are both empty
  double stack_iou = 0;     // Σ intersection / Σ union over the stack
  // Over slices whose truth body covers ≥ 1 % of the frame:
  int body_slices = 0;
  double mean_body_iou = 0, min_body_iou = 0;
  int min_body_slice = -1;
};
// `truth`: uint8 W×H×N NRRD (nonzero = body); `estimate`: N images W×H (nonzero = body).
MaskScore score_masks(const NrrdVolume& truth, const std::vector<cv::Mat>& estimate);

struct LabelScore {
  std::vector<double> accuracy;  // per slice; NaN where excluded or nothing counted
  std::uint64_t counted = 0, equal = 0;
  double overall = 0;  // equal / counted
  double worst = 0;
  int worst_slice = -1, scored_slices = 0;
};
// Counts pixels whose truth label is constant within `edge_px` (a (2·edge_px+1)² window: away
// from every class edge, the body outline included) and where truth or estimate is nonzero;
// a pixel is right when the estimate equals the truth. Slices in `excluded` (lost = black, or
// duplicated, in the truth) are skipped. `truth`: uint16 NRRD; `estimate`: 16-bit (or 8-bit)
// images.
LabelScore score_labels(const NrrdVolume& truth, const std::vector<cv::Mat>& estimate,
                        const std::vector<int>& excluded, int edge_px = 2);

struct Score {
  std::string truth_frame, estimate_frame;  // "frame" of each transforms.json ("" if absent)
  DriftScore drift;
  JumpScore jumps;
  bool has_mask = false, has_labels = false;
  MaskScore mask;
  LabelScore labels;
  // A streamed phantom (truth/transforms.json lists "truth_sample"): the slices the mask and label
  // scores and the drift over the body cover; their per-slice vectors follow this list. Empty:
  // every slice (truth/mask.nrrd, labels.nrrd).
  std::vector<int> truth_sample;
};
// Everything that the work folder holds: drift and jumps always (register/transforms.json is
// required; also the drift over slices with ≥ 1 % body, from truth/mask.nrrd or, for a streamed
// phantom, truth/sample/mask_NNNN.png), mask and labels when their folders hold an image for
// every slice scored.
Score score_work(const std::string& truth_dir, const std::string& work_dir);

// JSON of a score (NaN written as null), for reports and vispack-score --json.
nlohmann::json to_json(const Score& score);

}  // namespace vispack::phantom

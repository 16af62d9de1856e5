// Slice-to-slice registration of the colour stack and the CT → colour alignment
// (vispack-register; DESIGN.md sections 1, 2, 7; conventions in rigid.h and
// docs/ARCHITECTURE.md "Slice transforms").
//
// Method, per pair of slices (j, k), j < k ("phase+ecc"):
//   1. Each slice becomes a RegisterFrame once (prepare_frame): grey float levels (a coarse
//      level whose longer edge is about 256 px, and the ECC level at register.ecc_scale of full
//      resolution), its fiducials (find_fiducials), a pixel hash and a black flag. A frame is
//      shared by every pair it takes part in.
//   2. Coarse: Hann-windowed phase correlation at 0°, then ECC (MOTION_EUCLIDEAN) on the coarse
//      level. Only when that is not confident (correlation < 0.85, or ECC fails) does a sweep of
//      phase correlations at rotations −10°..10° (step 2.5°, refined by a parabola) seed a second
//      coarse ECC; the better one is kept. This finds block jumps of tens of pixels and several
//      degrees without paying for the sweep on ordinary neighbours.
//   3. ECC at ecc_scale from the coarse estimate (at most register.ecc_iterations iterations,
//      stopping when the correlation no longer improves). The final correlation coefficient is
//      the pair's quality. If ECC fails, the phase estimate is kept with quality <= 0.5.
//   "phase" stops after the sweep (quality = normalised correlation); "none" gives identities.
//
// Chaining without random walk: every non-black slice k is registered against its previous
// non-black slice and the one before it (edges k−1→k and k−2→k in the stack of usable
// slices). Those edges measure anatomy as well as drift: tissue that changes from slice to
// slice shifts the best match by a few hundredths of a pixel, consistently over several slices,
// so a chain of pair edges alone random-walks (tenths of a pixel over 64 slices). Fiducials fix
// that: the tubes in the gel do not change along the stack, so their positions tie every slice
// to a common frame. chain_transforms tracks the fiducials of each slice across the stack
// (on the grid of a first, pair-edge-only solution), and for each group of slices that see the
// same set of (at least two) fiducial tracks (each seen on at least 3 slices) adds one free
// "group frame" node with an edge to every slice of the group: the rigid fit of the group's
// mean fiducial positions to the slice's, weighted 25 × a pair edge (fiducials do not change
// along the stack, so they decide the slow part of the drift), dropped where one fiducial
// misfits by more than 1 px or the fit is more than 10 px from the pair-edge solution. The
// cumulative transforms are the weighted least-squares solution of all edges
// (solve_chain): rotations first, then shifts, each a banded linear system bordered by the
// group nodes. Without fiducials (none found, or fewer than two) the pair edges alone decide.
// Black slices (almost no signal) get no edges; their transform is linearly interpolated from
// the nearest usable neighbours and they are flagged black. An exact duplicate (identical
// pixels to the previous slice) is flagged duplicate_of and takes the original's transform.
// A jump is flagged at slice k when the motion between its usable predecessor and k (largest
// corner displacement, rigid_motion_px) exceeds register.jump_px.
//
// All functions are thread-safe (no shared state).
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/mask.h"
#include "vispack/pipeline/rigid.h"
#include "vispack/pipeline/stage.h"

namespace vispack::pipeline {

// A slice prepared for registration: grey float32 levels and flags. Immutable after creation.
struct RegisterFrame {
  cv::Size full_size;  // the observed slice's size
  cv::Mat coarse;      // CV_32F, longer edge ≈ 256 px (or full size if smaller), 5×5 Gaussian
  double coarse_scale = 1.0;  // coarse size / full size
  cv::Mat fine;               // CV_32F at ecc_scale, 5×5 Gaussian (may share data with coarse)
  double fine_scale = 1.0;
  bool black = false;                  // almost no signal: mean grey < 4 and standard deviation < 2
  std::uint64_t pixel_hash = 0;        // xxHash64 of the pixels (exact duplicate detection)
  std::vector<cv::Point2d> fiducials;  // find_fiducials of the slice (observed pixels)
};

// Fiducials of an RGB CV_8UC3 slice (other types: none): compact blobs that are not gel
// coloured (distance > 40 from the gel colour estimated on the slice border), lie in the gel
// (not the largest non-gel component, the body) and stay at least 2 coarse pixels inside the
// frame. Found on a level whose longer edge is about 256 px; each position is then the
// centroid, on the full-resolution slice, of the blob's coverage (the projection of each
// pixel's colour onto the gel→blob colour axis, 0.15 → 0 and 1.1 → 1, clamped). Sub-pixel
// accurate (about 0.05 px on the phantom). Returned in observed pixel coordinates, sorted by
// y then x. Pure and thread-safe.
std::vector<cv::Point2d> find_fiducials(const cv::Mat& rgb);

// Builds the frame from an RGB (or grey) CV_8U/CV_16U slice. Throws InputError on an empty or
// unsupported image.
RegisterFrame prepare_frame(const cv::Mat& slice, const RegisterOptions& options);

// The rigid transform between two slices: observed point p_j of slice j corresponds to
// p_k = c + R(rotation)(p_j − c) + d in slice k, so T_k = relative ∘ T_j (T as in rigid.h).
struct PairEstimate {
  Rigid relative;
  double quality = 0.0;   // [0, 1]: ECC correlation coefficient ("phase": peak response)
  double response = 0.0;  // phase-correlation peak of the coarse step
  bool ecc_ok = false;    // the ECC refinement converged
};

// Registers slice k (`to`) against slice j (`from`). Both frames must come from the same
// options and slice size (throws Error otherwise). With `initial` (a good estimate, e.g. a
// skip edge composed from two measured neighbour edges) and method "phase+ecc", only the fine
// ECC step runs from it; the full coarse-to-fine search runs if that fails.
PairEstimate estimate_pair(const RegisterFrame& from, const RegisterFrame& to,
                           const RegisterOptions& options, const Rigid* initial = nullptr);

// One measured edge of the pair graph (from < to, stack indices).
struct PairEdge {
  int from = 0, to = 0;
  Rigid relative;
  double weight = 1.0;  // > 0; the least-squares weight
};

// Weighted least-squares cumulative transforms T_0..T_{n−1} from the edges, with T_0 = identity
// (the reference). Nodes n..n+free_nodes−1 are free frames (a fiducial group's frame): edges
// may join them to any slice (in either direction; from < to is not required for them); their
// solved transforms follow the slices' in the result (size n + free_nodes). Slices not reached
// by any edge from slice 0 get the identity; callers interpolate them (black slices). Cost:
// O(n · band² + free_nodes · n · band), band = the longest slice-to-slice edge. Throws Error on
// an edge outside [0, n + free_nodes) or joining a node to itself.
std::vector<Rigid> solve_chain(int n, const std::vector<PairEdge>& edges, int free_nodes = 0);

// Everything registration decides about one slice, before chaining (what a shard computes).
struct SlicePairs {
  int index = 0;
  bool black = false;
  std::optional<int> duplicate_of;
  std::uint64_t pixel_hash = 0;
  std::vector<PairEdge> edges;         // edges ending at this slice (to == index)
  double quality = 1.0;                // of the edge from the previous usable slice
  std::vector<cv::Point2d> fiducials;  // the slice's fiducials (RegisterFrame::fiducials)
};
nlohmann::json to_json(const SlicePairs& pairs);
// Throws FormatError naming `what` on a malformed record.
SlicePairs slice_pairs_from_json(const nlohmann::json& j, const std::string& what);

// Computes the edges of slices [first, last) of a stack whose frames `frame(i)` returns (any
// index in [max(0, first − 4), last) may be asked for; a frame is asked for at most once per
// call and the caller may cache). Edges reach back over black slices to the previous two
// usable ones, looking back at most 4 slices. The nearest edges run first (full search); each
// skip edge then starts from the composition of the two nearest edges it spans (fine ECC only).
// The look-back slices before `first` get their nearest edges too (not returned), so a shard
// computes exactly the records of an unsharded run. Runs pairs on `threads` threads.
std::vector<SlicePairs> compute_pairs(int first, int last,
                                      const std::function<RegisterFrame(int)>& frame,
                                      const RegisterOptions& options, int threads);

// Chains the per-slice records of a whole stack (pairs[k].index == k) into transforms:
// solve_chain over the pair edges and the fiducial groups (see the top of this file),
// interpolation over black slices, duplicates copied, jumps flagged against `jump_px` for a
// slice of `size`. `fiducial_groups` (optional) receives the number of fiducial groups used.
std::vector<SliceTransform> chain_transforms(const std::vector<SlicePairs>& pairs, cv::Size size,
                                             double jump_px, int* fiducial_groups = nullptr);

// ---- CT → colour ----

// The outlines come from mask.h (ct_body_mask, colour_body_mask).
// Refines `initial` (ct_to_rgb, rigid.h) so that the CT outline, mapped onto the output grid,
// matches the colour outline: ECC (MOTION_AFFINE) on blurred outlines at reduced resolution,
// projected to the nearest similarity. `ct_outline` and `rgb_outline` are 0/255 CV_8U.
// Returns `initial` unchanged (and *ok = false) if ECC fails or moves too far (> 25 % of the
// image or > 20 % in scale).
Similarity align_ct_to_rgb(const cv::Mat& ct_outline, const cv::Mat& rgb_outline,
                           const Similarity& initial, bool* ok = nullptr);

// ---- the stage ----

// vispack-register: reads the rgb stack (and CT if configured), writes
//   <work>/register/pairs/pairs_NNNN.json   per-slice edges (the sharded part)
//   <work>/register/transforms.json         chained transforms + ct_to_rgb
//   <work>/register/registered/rgb_NNNN.png the colour slices resampled onto the output grid
//   <work>/register/report.json             time, throughput, quality summary, jumps
// Sharded runs (options.slices = "A:B") compute the pair records of [A, B) (reading slices down
// to A−4 for the edges into A). The run that finds every slice's pair record present (whichever
// shard finishes last, or the unsharded run) chains them and writes transforms.json; a shard
// writes registered slices of its range only when transforms.json covers the whole stack. So a
// scheduler runs all shards, then runs the shards (or one unsharded run) again: the second pass
// reuses the pair records and only chains and resamples.
StageResult run_register_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

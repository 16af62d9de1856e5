// Slice-to-slice (pair) estimates and the per-slice records a (sharded) register run computes.
//
// Method, per pair of slices (j, k), j < k ("phase+ecc"):
//   1. Coarse: Hann-windowed phase correlation at 0°, then ECC (MOTION_EUCLIDEAN) on the coarse
//      level. Only when that is not confident (correlation < 0.85, or ECC fails) does a sweep of
//      phase correlations at rotations −10°..10° (step 2.5°, refined by a parabola) seed a second
//      coarse ECC; the better one is kept. This finds block jumps of tens of pixels and several
//      degrees without paying for the sweep on ordinary neighbours.
//   2. ECC at ecc_scale from the coarse estimate (at most register.ecc_iterations iterations,
//      stopping when the correlation no longer improves), after a first pass at half ecc_scale
//      where that lies well above the coarse level (2048×1216 at ecc_scale 0.5: 512 then 1024
//      px wide). Either pass also stops after an update under 0.02 full-resolution px
//      (EccOptions::min_step_px). A result more than 4 coarse pixels from the start is a
//      failure; either pass stops at its first iterate twice that far (ecc.h
//      kEccRunawayFactor). Where the first pass's correlation is under 0.9 (the slices differ
//      in anatomy more than they move; ECC creeps), the fine pass has at most 10 iterations
//      and one still moving at the 10th is a failure too. The final
//      correlation coefficient is the pair's quality. If ECC fails, the phase estimate is kept
//      with quality <= 0.5.
//   "phase" stops after the sweep (quality = normalised correlation); "none" gives identities.
// A pair estimate measures drift AND anatomy: tissue that changes from slice to slice (an
// outline that moves as the stack rises) moves the best match. How the global solve keeps that
// from accumulating is in register/solve.h and docs/ARCHITECTURE.md "Registration".
// All functions are thread-safe (no shared state).
#pragma once

#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/ct_anchor.h"
#include "vispack/pipeline/register/frame.h"

namespace vispack::pipeline {

// The rigid transform between two slices: observed point p_j of slice j corresponds to
// p_k = c + R(rotation)(p_j − c) + d in slice k, so T_k = relative ∘ T_j (T as in
// imaging/transforms.h).
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
  double weight = 1.0;  // > 0; 1 when ECC converged, 0.05 when only the phase estimate exists
};

// Everything registration decides about one slice before the global solve (what a shard
// computes and stores in work/register/pairs/pairs_NNNN.json).
struct SlicePairs {
  int index = 0;
  bool black = false;
  std::optional<int> duplicate_of;
  std::uint64_t pixel_hash = 0;
  std::vector<PairEdge> edges;           // edges ending at this slice (to == index)
  double quality = 1.0;                  // of the edge from the previous usable slice
  std::vector<cv::Point2d> fiducials;    // the slice's fiducials (RegisterFrame::fiducials)
  std::optional<AnchorEstimate> anchor;  // the CT anchor (absent: no CT slice, or not asked)
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
// computes exactly the records of an unsharded run. `anchor` (optional) is called once for
// every non-black slice of [first, last) with its frame and fills SlicePairs::anchor (it must
// be thread-safe). Runs pairs on `threads` threads.
std::vector<SlicePairs> compute_pairs(
    int first, int last, const std::function<RegisterFrame(int)>& frame,
    const RegisterOptions& options, int threads,
    const std::function<std::optional<AnchorEstimate>(int, const RegisterFrame&)>& anchor = {});

}  // namespace vispack::pipeline

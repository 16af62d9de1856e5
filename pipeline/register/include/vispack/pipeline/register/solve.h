// The global solve: every slice's transform T_k from all measurements at once.
//
// Measurements (register/pair.h, register/ct_anchor.h):
//   anchor a_k   T_k measured against CT slice k: absolute, drift-free, noisy (σ_a ≈ 0.05 CT px
//                nominal, inflated from the residuals),
//                weighted by its confidence; the rotation by confidence · lever² (the lever from
//                the CT template's gradients: a featureless patch says little about rotation).
//   pair   P_jk  T_k ∘ T_j⁻¹ between neighbours: precise (σ_p ≈ 0.05 px) but it also measures
//                the anatomy: P_jk = true relative motion + b_k, b_k the apparent motion of
//                tissue that changes along z (a bias, not noise: the same sign for many slices).
//   fiducial     tubes in the gel: a rigid fit of each slice's tubes to their group's mean.
// The CT-anchored solve (solve_stack, anchor mode "ct") minimises, over θ_k then d_k (rotation
// first; the shift rows are linear once the rotations are known):
//   Σ_k w_a,k |T_k − a_k|²                                            (anchors)
// + Σ_k w_c,k |(T_{k+1} ⊖ T_k)/g_{k+1} − (T_k ⊖ T_{k−1})/g_k − (P_{k,k+1}/g_{k+1} −
// P_{k−1,k}/g_k)|²
//                                                                     (pair CURVATURE terms)
// + Σ_k w_1 |T_k ⊖ T_{k−1} − P_{k−1,k}|²                              (weak first-order pair terms)
// + Σ_k w_w |T_k ⊖ T_{k−1}|² / g_k                                     (random-walk prior)
// + fiducial group terms,
// with g the slice gap between usable neighbours and A ⊖ B the relative transform. Pair
// measurements enter (almost) only through the DIFFERENCE of consecutive pair estimates, so a
// constant bias b cancels exactly, a bias that changes by Δb per slice enters like a curvature
// error of Δb, and its effect is bounded by ≈ Δb·L² where L = (w_c/w_a)^¼ ≈ 3 slices (not by
// b·n as in integration); the weak first-order terms (w_1 = 0.04 w_a: crossover length 0.2
// slices) leak at most ≈ 0.2·b. Nothing in the solve integrates b over the stack, so the error
// does not grow with the stack's length. docs/ARCHITECTURE.md "Registration" has the argument.
// Both pair terms weigh what the pair can know: σ_p grows as (R0 / r)² for a body of radius r
// below R0 (a quarter of the mean edge; r the smaller body the pair joins), and the rotation's
// lever is r, not R0. Where the body is small (the top of a head, the feet) a pair estimate
// moves with the anatomy by a degree while the anchor stays within a tenth: the anchors decide
// there, not the pairs (the first-order terms took R0's weight for every body until the male
// phantom's head cap showed it: docs/BENCHMARKS.md "Every body part").
// Before the solve, pair edges are dropped where they contradict both (confident) anchors they
// join, where either slice shows almost no body, or where they claim a jump two confident
// anchors cannot confirm. After each solve, every class of measurement gets a noise scale from
// its residuals (median, inflate only) and each term a Cauchy weight (3 passes): a wrong anchor
// on a tiny patch or a lost pair at the stack's end does not pull its neighbours. A weak
// smoothness prior (second differences, σ 0.5 px / 0.05°) and a weak random-walk prior (first
// differences towards no motion, σ 0.6 px / 0.1° per slice: twice the drift of a real stack)
// decide where nothing else does (the ends of the stack, empty slices, a small body's rotation);
// jumps cut both. The random-walk prior pulls towards zero motion, never towards a measurement,
// so it integrates nothing. Fiducial groups (tubes) add free group frames.
// Marked jumps (overrides) and missing pair edges cut the pair terms.
// Without CT: anchor mode "fiducials" (the legacy chain plus fiducial groups, slice 0 the
// reference) or "none" (the chain regularised towards no drift over ~100 slices: absolute drift
// is not observable and the stage says so).
// Black slices are interpolated between usable neighbours, duplicates copy their original, and
// a jump is flagged where the solved motion between usable neighbours exceeds jump_px (or a
// person marked one). All functions are pure and thread-safe.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/overrides.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/pair.h"

namespace vispack::pipeline {

// Weighted least-squares cumulative transforms T_0..T_{n−1} from the edges, with T_0 = identity
// (the reference). Nodes n..n+free_nodes−1 are free frames (a fiducial group's frame): edges
// may join them to any slice (in either direction; from < to is not required for them); their
// solved transforms follow the slices' in the result (size n + free_nodes). Slices not reached
// by any edge from slice 0 get the identity; callers interpolate them (black slices). Cost:
// O(n · band² + free_nodes · n · band), band = the longest slice-to-slice edge. Throws Error on
// an edge outside [0, n + free_nodes) or joining a node to itself.
std::vector<Rigid> solve_chain(int n, const std::vector<PairEdge>& edges, int free_nodes = 0);

// The slice-0-referenced chain of a whole stack (pairs[k].index == k): solve_chain over the
// pair edges and the fiducial groups (each group of slices that sees the same >= 2 fiducial
// tracks gets a free frame node with an edge to each of its slices, weighted 25 × a pair
// edge), interpolation over black slices, duplicates copied, jumps flagged against `jump_px`
// for a slice of `size`. `fiducial_groups` (optional) receives the number of groups used.
std::vector<SliceTransform> chain_transforms(const std::vector<SlicePairs>& pairs, cv::Size size,
                                             double jump_px, int* fiducial_groups = nullptr);

struct StackSolveOptions {
  std::string anchor = "ct";  // resolved mode: "ct", "fiducials" or "none"
  double jump_px = 6.0;
  std::vector<SliceOverride> overrides;
};

struct StackSolve {
  // With anchor mode "ct", each slice's extra holds "anchor_confidence" ([0, 1]; 0: the CT
  // could not anchor it) and, where the anchor exists, "anchor_residual_px" (largest
  // displacement, corners and centre, between the anchor and the solved transform).
  std::vector<SliceTransform> slices;
  std::string frame;  // "ct", "fiducials" or "slice0"
  int fiducial_groups = 0;
  int anchors_used = 0;          // slices whose anchor took part
  int anchors_downweighted = 0;  // of those, down-weighted as outliers (residual > 3σ)
  int pairs_rejected = 0;        // pair edges dropped for contradicting both their anchors
};

// Solves the stack (see the top of this file). Throws Error on records out of order.
StackSolve solve_stack(const std::vector<SlicePairs>& pairs, cv::Size size,
                       const StackSolveOptions& options);

}  // namespace vispack::pipeline

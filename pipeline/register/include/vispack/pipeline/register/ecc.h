// Enhanced correlation coefficient (ECC) alignment of two images under a Euclidean motion
// (rotation + translation): the iteration of Evangelidis & Psarakis (2008) exactly as OpenCV's
// cv::findTransformECC runs it for MOTION_EUCLIDEAN without masks (forward additive: the input
// and its gradients warped onto the template each iteration, the photometric scale λ solved in
// closed form, the same start, termination and failure conditions), computed in one fused pass
// per iteration: each template pixel's bilinear samples of the input and of its two gradients
// are taken once and only the ~25 sums the update needs are accumulated (in double), instead of
// four warped images, a Jacobian image and a dozen whole-image passes. Bilinear weights are exact
// (OpenCV's warpAffine rounds them to 1/32 pixel), so results agree with OpenCV's to within
// that rounding, not bit for bit (tests/pipeline/test_ecc.cpp; tests/bench/register_bench.cpp
// times both on the same images).
//
// Coordinates: pixel centres at integer (x, y), x to the right, y down. `warp` maps template
// pixels to input pixels: input(warp · (x, y, 1)) is compared with template(x, y).
// Pure and thread-safe; runs on the calling thread.
#pragma once

#include <functional>
#include <optional>

#include <opencv2/core.hpp>

namespace vispack::pipeline {

struct EccOptions {
  int iterations = 50;  // at most this many updates
  double eps = 1e-5;    // stop when the correlation changes by less than this
  int blur_size = 1;    // Gaussian blur (odd kernel size, σ from the size) of both images first
  // Optional (not in OpenCV; 0 = off): also stop, as converged, after an update that moves no
  // template pixel by more than this many pixels (of the template's grid). The bound used is
  // |Δt| + |Δθ| · (the template's diagonal), never below the largest displacement. The
  // correlation's gain alone (eps) needs one more pass over the image after a step this small,
  // and on a slowly converging path keeps going long after the steps have become negligible.
  double min_step_px = 0.0;
  // Optional (not in OpenCV): called with the warp after each update; returning true ends the
  // refinement as a failure (nullopt, `warp` holding that update). A caller that rejects a result
  // too far from its start says so here and stops an iteration that has run away (on slices
  // whose anatomy differs, ECC can creep tens of pixels a few tenths at a time until the limit)
  // instead of paying for the remaining iterations. Must be thread-safe if shared.
  std::function<bool(const cv::Matx23d&)> diverged;
  // Optional (not in OpenCV): called after each update (after `diverged`) with the correlation
  // measured before that update (what a stop there would return) and the update's number (1, 2,
  // ...); returning true ends the refinement as a failure (nullopt, `warp` holding that update).
  // A caller that stops following a pair whose correlation stays low while its iterate keeps
  // moving says so here (register/pair.cpp). Must be thread-safe if shared.
  std::function<bool(double rho, int update)> give_up;
};

// How much farther than the caller's own rejection limit an iterate must lie for `diverged` to end
// the iteration: a path may overshoot its limit and come back (on the `anatomy` 5:1 case, ending
// at the limit itself moved a mask slice's IoU by 0.001); the runaway paths this is for leave by
// tens of times.
inline constexpr double kEccRunawayFactor = 2.0;

// Refines `warp` (a rotation + translation, template → input pixels; its rotation part must be
// a rotation) so that the warped input best correlates with `tmpl`, and returns the correlation
// coefficient measured before the last update, in [-1, 1]. It stops after `iterations` updates,
// when the correlation changed by less than `eps` between two updates, or (min_step_px > 0)
// after an update smaller than min_step_px. Returns nullopt where OpenCV would
// throw: the images are uncorrelated or do not overlap (λ's denominator ≤ 0), no template pixel
// maps into the input, or a value is not finite; `warp` then holds the last estimate.
// tmpl and input: one channel, CV_8U or CV_32F, any sizes (at least 3 × 3); not modified.
std::optional<double> ecc_euclidean(const cv::Mat& tmpl, const cv::Mat& input, cv::Matx23d& warp,
                                    const EccOptions& options);

}  // namespace vispack::pipeline

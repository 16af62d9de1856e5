// The matrices of the stack's transforms (core/transform_types.h: Rigid for a colour slice's
// drift, Similarity for ct_to_rgb) and the resampling, in the convention of
// docs/ARCHITECTURE.md ("Slice transforms"):
//
//   slice k:   a point q of the output (registered) grid appears in the observed slice at
//              p = c + R(θ_k)(q − c) + d_k,   c = ((W−1)/2, (H−1)/2),
//              R(θ) = [[cos θ, −sin θ], [sin θ, cos θ]] acting on (x, y) pixel coordinates
//              (x = column, y = row downwards), θ in degrees, d in pixels.
//   ct_to_rgb: a CT pixel u lands on the output grid at q = c + s·R(θ)(u − c_ct) + d.
//
// Registration resamples registered(q) = observed(p), i.e. cv::warpAffine with the q → p matrix
// and cv::WARP_INVERSE_MAP. All functions here are pure (no state) and thread-safe.
#pragma once

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/transform_types.h"

namespace vispack::pipeline {

// Pixel centre c = ((W−1)/2, (H−1)/2) of a W×H image.
inline cv::Point2d image_centre(int width, int height) {
  return {(width - 1) * 0.5, (height - 1) * 0.5};
}
inline cv::Point2d image_centre(const cv::Size& size) {
  return image_centre(size.width, size.height);
}

// The 2×3 matrix of p = c + R(θ)(q − c) + d (maps output-grid q to observed p).
cv::Matx23d rigid_matrix(const Rigid& t, cv::Point2d centre);

// The 2×3 matrix of q = c_to + s·R(θ)(u − c_from) + d (maps CT pixel u to output q).
cv::Matx23d similarity_matrix(const Similarity& t, cv::Point2d c_from, cv::Point2d c_to);

// Inverse of an invertible 2×3 affine matrix. Throws vispack::Error if singular.
cv::Matx23d invert_affine(const cv::Matx23d& m);

// a ∘ b: (a ∘ b)(x) = a(b(x)).
cv::Matx23d compose_affine(const cv::Matx23d& a, const cv::Matx23d& b);

// The rigid transform (about `centre`) closest to a 2×3 matrix (rotation from the polar
// decomposition, shift such that the centre maps exactly).
Rigid rigid_from_matrix(const cv::Matx23d& m, cv::Point2d centre);

// The similarity closest to a 2×3 matrix m (u → q): scale = sqrt|det|, rotation from the
// polar decomposition, shift such that c_from maps exactly.
Similarity similarity_from_matrix(const cv::Matx23d& m, cv::Point2d c_from, cv::Point2d c_to);

// Re-expresses a full-resolution 2×3 matrix for images resampled by `scale` (INTER_AREA-style
// resizing, pixel centres: x_s = (x + 0.5)·scale − 0.5), and back.
cv::Matx23d scale_affine(const cv::Matx23d& m, double scale);
cv::Matx23d unscale_affine(const cv::Matx23d& m_scaled, double scale);

// Largest displacement (pixels) of the corners and centre of a W×H image under the rigid
// transform compared with the identity; the "motion" compared with register.jump_px.
double rigid_motion_px(const Rigid& t, cv::Size size);

// Resamples an observed slice onto the output grid: out(q) = observed(p(q)). `interpolation`
// is cv::INTER_LINEAR or cv::INTER_NEAREST; outside pixels take `border` (constant).
cv::Mat resample_rigid(const cv::Mat& observed, const Rigid& t, int interpolation,
                       const cv::Scalar& border = cv::Scalar());

// The 2×3 matrix mapping an output-grid point q to CT pixel u: the inverse of ct_to_rgb's
// similarity_matrix(t, ct_centre, centre). Use with warpAffine(..., WARP_INVERSE_MAP).
cv::Matx23d output_to_ct(const Similarity& t, cv::Point2d centre, cv::Point2d ct_centre);

// The output grid of a stack's transforms: its centre c and its size (W, H).
inline cv::Point2d grid_centre(const StackTransforms& t) {
  return {t.center_px[0], t.center_px[1]};
}
inline cv::Size grid_size(const StackTransforms& t) {
  return {t.width, t.height};
}

}  // namespace vispack::pipeline

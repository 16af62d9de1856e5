// CT → colour alignment (similarity) from body outlines. See register.h.
#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "vispack/common/error.h"
#include "vispack/pipeline/register.h"

namespace vispack::pipeline {

Similarity align_ct_to_rgb(const cv::Mat& ct_outline, const cv::Mat& rgb_outline,
                           const Similarity& initial, bool* ok) {
  if (ok) *ok = false;
  if (ct_outline.empty() || rgb_outline.empty() || cv::countNonZero(ct_outline) == 0 ||
      cv::countNonZero(rgb_outline) == 0)
    return initial;
  const cv::Point2d c_ct = image_centre(ct_outline.size());
  const cv::Point2d c_out = image_centre(rgb_outline.size());
  // Working grid: the output grid scaled so its longer edge is at most 512 px.
  const double s = std::min(1.0, 512.0 / std::max(rgb_outline.cols, rgb_outline.rows));
  cv::Mat tmpl;
  rgb_outline.convertTo(tmpl, CV_32F, 1.0 / 255.0);
  if (s < 1.0) cv::resize(tmpl, tmpl, cv::Size(), s, s, cv::INTER_AREA);
  const double sx = double(tmpl.cols) / rgb_outline.cols;
  // Initial map working grid → CT, and the CT outline resampled onto the working grid with it.
  const cv::Matx23d out_to_ct = invert_affine(similarity_matrix(initial, c_ct, c_out));
  const double o = 0.5 * sx - 0.5;
  const cv::Matx23d work_to_out{1.0 / sx, 0, -o / sx, 0, 1.0 / sx, -o / sx};
  const cv::Matx23d w0 = compose_affine(out_to_ct, work_to_out);
  cv::Mat ct_f, warped;
  ct_outline.convertTo(ct_f, CV_32F, 1.0 / 255.0);
  cv::warpAffine(ct_f, warped, cv::Mat(w0), tmpl.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                 cv::BORDER_CONSTANT, cv::Scalar(0));
  // Blurred outlines widen the basin of convergence; two passes, wide then narrow.
  cv::Matx23d a = cv::Matx23d(1, 0, 0, 0, 1, 0);
  try {
    for (double sigma : {6.0, 2.0}) {
      cv::Mat t, w;
      cv::GaussianBlur(tmpl, t, cv::Size(0, 0), sigma);
      cv::GaussianBlur(warped, w, cv::Size(0, 0), sigma);
      cv::Mat warp(2, 3, CV_32F);
      for (int i = 0; i < 6; ++i)
        warp.at<float>(i / 3, i % 3) = float(a.val[i]);
      cv::findTransformECC(
          t, w, warp, cv::MOTION_AFFINE,
          cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 100, 1e-6),
          cv::noArray(), 1);
      for (int i = 0; i < 6; ++i)
        a.val[i] = warp.at<float>(i / 3, i % 3);
    }
  } catch (const cv::Exception&) {
    return initial;
  }
  // Working grid → CT = w0 ∘ a; output → CT = w0 ∘ a ∘ (output → working).
  const cv::Matx23d out_to_work{sx, 0, o, 0, sx, o};
  const cv::Matx23d m = compose_affine(w0, compose_affine(a, out_to_work));
  Similarity refined = similarity_from_matrix(invert_affine(m), c_ct, c_out);
  const double max_shift = 0.25 * std::max(rgb_outline.cols, rgb_outline.rows);
  if (!std::isfinite(refined.scale) || std::abs(refined.scale / initial.scale - 1.0) > 0.2 ||
      std::hypot(refined.dx_px - initial.dx_px, refined.dy_px - initial.dy_px) > max_shift)
    return initial;
  if (ok) *ok = true;
  return refined;
}

}  // namespace vispack::pipeline

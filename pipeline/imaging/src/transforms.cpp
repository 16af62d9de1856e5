// The matrices of the stack's transforms. See imaging/transforms.h.
#include "vispack/pipeline/imaging/transforms.h"

#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"

namespace vispack::pipeline {

cv::Matx23d rigid_matrix(const Rigid& t, cv::Point2d centre) {
  const double a = radians(t.rotation_deg), co = std::cos(a), si = std::sin(a);
  // p = R q + (c − R c + d)
  const double tx = centre.x - (co * centre.x - si * centre.y) + t.dx_px;
  const double ty = centre.y - (si * centre.x + co * centre.y) + t.dy_px;
  return {co, -si, tx, si, co, ty};
}

cv::Matx23d similarity_matrix(const Similarity& t, cv::Point2d c_from, cv::Point2d c_to) {
  const double a = radians(t.rotation_deg);
  const double co = t.scale * std::cos(a), si = t.scale * std::sin(a);
  // q = sR u + (c_to − sR c_from + d)
  const double tx = c_to.x - (co * c_from.x - si * c_from.y) + t.dx_px;
  const double ty = c_to.y - (si * c_from.x + co * c_from.y) + t.dy_px;
  return {co, -si, tx, si, co, ty};
}

cv::Matx23d invert_affine(const cv::Matx23d& m) {
  const double det = m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0);
  if (!(std::abs(det) > 1e-12)) throw Error(cat("invert_affine: singular matrix (det ", det, ")"));
  const double i00 = m(1, 1) / det, i01 = -m(0, 1) / det;
  const double i10 = -m(1, 0) / det, i11 = m(0, 0) / det;
  return {i00, i01, -(i00 * m(0, 2) + i01 * m(1, 2)), i10, i11, -(i10 * m(0, 2) + i11 * m(1, 2))};
}

cv::Matx23d compose_affine(const cv::Matx23d& a, const cv::Matx23d& b) {
  cv::Matx23d r;
  for (int i = 0; i < 2; ++i) {
    for (int j = 0; j < 2; ++j)
      r(i, j) = a(i, 0) * b(0, j) + a(i, 1) * b(1, j);
    r(i, 2) = a(i, 0) * b(0, 2) + a(i, 1) * b(1, 2) + a(i, 2);
  }
  return r;
}

Rigid rigid_from_matrix(const cv::Matx23d& m, cv::Point2d centre) {
  Rigid t;
  t.rotation_deg = degrees(std::atan2(m(1, 0) - m(0, 1), m(0, 0) + m(1, 1)));
  const double px = m(0, 0) * centre.x + m(0, 1) * centre.y + m(0, 2);
  const double py = m(1, 0) * centre.x + m(1, 1) * centre.y + m(1, 2);
  t.dx_px = px - centre.x;
  t.dy_px = py - centre.y;
  return t;
}

Similarity similarity_from_matrix(const cv::Matx23d& m, cv::Point2d c_from, cv::Point2d c_to) {
  Similarity t;
  t.scale = std::sqrt(std::abs(m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0)));
  t.rotation_deg = degrees(std::atan2(m(1, 0) - m(0, 1), m(0, 0) + m(1, 1)));
  const double qx = m(0, 0) * c_from.x + m(0, 1) * c_from.y + m(0, 2);
  const double qy = m(1, 0) * c_from.x + m(1, 1) * c_from.y + m(1, 2);
  t.dx_px = qx - c_to.x;
  t.dy_px = qy - c_to.y;
  return t;
}

cv::Matx23d scale_affine(const cv::Matx23d& m, double scale) {
  // x_s = s·x + o with o = 0.5·s − 0.5 on both sides: m_s = S m S⁻¹.
  const double o = 0.5 * scale - 0.5;
  const cv::Matx23d s{scale, 0, o, 0, scale, o};
  const cv::Matx23d s_inv{1.0 / scale, 0, -o / scale, 0, 1.0 / scale, -o / scale};
  return compose_affine(s, compose_affine(m, s_inv));
}

cv::Matx23d unscale_affine(const cv::Matx23d& m_scaled, double scale) {
  return scale_affine(m_scaled, 1.0 / scale);
}

double rigid_motion_px(const Rigid& t, cv::Size size) {
  const cv::Point2d c = image_centre(size);
  const cv::Matx23d m = rigid_matrix(t, c);
  double worst = 0.0;
  const double xs[3] = {0.0, c.x, size.width - 1.0}, ys[3] = {0.0, c.y, size.height - 1.0};
  for (double x : xs) {
    for (double y : ys) {
      const double px = m(0, 0) * x + m(0, 1) * y + m(0, 2);
      const double py = m(1, 0) * x + m(1, 1) * y + m(1, 2);
      worst = std::max(worst, std::hypot(px - x, py - y));
    }
  }
  return worst;
}

cv::Mat resample_rigid(const cv::Mat& observed, const Rigid& t, int interpolation,
                       const cv::Scalar& border) {
  cv::Mat out;
  cv::warpAffine(observed, out, cv::Mat(rigid_matrix(t, image_centre(observed.size()))),
                 observed.size(), interpolation | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT,
                 border);
  return out;
}

cv::Matx23d output_to_ct(const Similarity& t, cv::Point2d centre, cv::Point2d ct_centre) {
  return invert_affine(similarity_matrix(t, ct_centre, centre));
}

// ---- transforms.json ----

}  // namespace vispack::pipeline

// outline_distance and shape_blend_hu (ct_shape_blend.h).
#include "vispack/pipeline/imaging/ct_shape_blend.h"

#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"

namespace vispack::pipeline {
namespace {

// The distance of a slice without a pixel on one side (no outline).
constexpr float kNoOutline = 1e4f;
// The smallest HU slope (HU per CT pixel) the sub-pixel distance divides by: a flat, noisy
// stretch at the level does not place the outline far from the pixel.
constexpr float kMinSlopeHuPerPx = 50.f;

// Whether `hu` has pixels on both sides of `level`.
bool has_outline(const cv::Mat& hu, double level) {
  const int n_in = cv::countNonZero(hu > level);
  return n_in > 0 && n_in < int(hu.total());
}

}  // namespace

cv::Mat outline_distance(const cv::Mat& hu, double level) {
  if (hu.type() != CV_32FC1) throw Error("outline_distance: the CT slice is not CV_32F HU");
  const cv::Mat inside = hu > level;
  const int n_in = cv::countNonZero(inside);
  if (n_in == 0) return cv::Mat(hu.size(), CV_32F, cv::Scalar(kNoOutline));
  if (n_in == int(hu.total())) return cv::Mat(hu.size(), CV_32F, cv::Scalar(-kNoOutline));
  // Distances to the nearest pixel of the other side (pixel centres).
  cv::Mat d_in, d_out;
  cv::distanceTransform(inside, d_in, cv::DIST_L2, cv::DIST_MASK_PRECISE);
  cv::distanceTransform(~inside, d_out, cv::DIST_L2, cv::DIST_MASK_PRECISE);
  // The edge: pixels 8-adjacent to the other side.
  cv::Mat grown, shrunk;
  cv::dilate(inside, grown, cv::Mat());
  cv::erode(inside, shrunk, cv::Mat(), cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  cv::Mat gx, gy;
  cv::Sobel(hu, gx, CV_32F, 1, 0, 3, 1.0 / 8.0, 0.0, cv::BORDER_REPLICATE);
  cv::Sobel(hu, gy, CV_32F, 0, 1, 3, 1.0 / 8.0, 0.0, cv::BORDER_REPLICATE);
  cv::Mat phi(hu.size(), CV_32F);
  const float lv = float(level);
  for (int y = 0; y < hu.rows; ++y) {
    const float* h = hu.ptr<float>(y);
    const std::uint8_t* in = inside.ptr<std::uint8_t>(y);
    const std::uint8_t* g = grown.ptr<std::uint8_t>(y);
    const std::uint8_t* s = shrunk.ptr<std::uint8_t>(y);
    const float* di = d_in.ptr<float>(y);
    const float* dout = d_out.ptr<float>(y);
    const float* ax = gx.ptr<float>(y);
    const float* ay = gy.ptr<float>(y);
    float* p = phi.ptr<float>(y);
    for (int x = 0; x < hu.cols; ++x) {
      const bool edge = in[x] ? !s[x] : g[x] != 0;
      if (!edge) {
        p[x] = in[x] ? -(di[x] - 0.5f) : dout[x] - 0.5f;
        continue;
      }
      const float slope = std::max(kMinSlopeHuPerPx, std::sqrt(ax[x] * ax[x] + ay[x] * ay[x]));
      const float d = (lv - h[x]) / slope;
      p[x] = in[x] ? std::clamp(d, -1.f, -1e-3f) : std::clamp(d, 1e-3f, 1.f);
    }
  }
  return phi;
}

cv::Mat shape_blend_hu(const cv::Mat& hu_below, const cv::Mat& hu_above, double w_above,
                       double level) {
  if (hu_below.size() != hu_above.size() || hu_below.type() != CV_32FC1 ||
      hu_above.type() != CV_32FC1)
    throw Error("shape_blend_hu: the two CT slices differ in size or are not CV_32F HU");
  const double w = std::clamp(w_above, 0.0, 1.0);
  cv::Mat blended;
  cv::addWeighted(hu_below, 1.0 - w, hu_above, w, 0.0, blended);
  if (!has_outline(hu_below, level) && !has_outline(hu_above, level)) return blended;
  const cv::Mat phi_below = outline_distance(hu_below, level);
  const cv::Mat phi_above = outline_distance(hu_above, level);
  cv::Mat phi;
  cv::addWeighted(phi_below, 1.0 - w, phi_above, w, 0.0, phi);
  const float lv = float(level), slope = float(kShapeSlopeHuPerPx);
  for (int y = 0; y < phi.rows; ++y) {
    const float* p = phi.ptr<float>(y);
    float* b = blended.ptr<float>(y);
    for (int x = 0; x < phi.cols; ++x) {
      const float shaped = lv - slope * p[x];
      const bool same_side = (p[x] < 0) == (b[x] > lv);
      if (std::abs(p[x]) < 1.f || !same_side) b[x] = shaped;
    }
  }
  return blended;
}

}  // namespace vispack::pipeline

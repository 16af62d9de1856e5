// QC pictures of the register stage. See register/qc.h.
#include "vispack/pipeline/register/qc.h"
#include "vispack/pipeline/imaging/transforms.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <opencv2/imgproc.hpp>

namespace vispack::pipeline {

cv::Mat shrink_to_edge(const cv::Mat& image, int max_edge) {
  const double s = std::min(1.0, double(max_edge) / std::max(image.cols, image.rows));
  cv::Mat out;
  if (s < 1.0) {
    cv::resize(image, out, cv::Size(), s, s, cv::INTER_AREA);
  } else {
    out = image.clone();
  }
  return out;
}

cv::Mat draw_ct_overlay(const cv::Mat& registered, const cv::Mat& ct_hu,
                        const Similarity& ct_to_rgb, double hu_threshold, int max_edge,
                        cv::Size grid) {
  if (grid.empty()) grid = registered.size();
  cv::Mat out = shrink_to_edge(registered, max_edge);
  if (ct_hu.empty()) return out;
  // Small grid → output grid → CT.
  const double sx = double(out.cols) / grid.width, sy = double(out.rows) / grid.height;
  const cv::Matx23d small_to_out{1.0 / sx, 0, 0.5 / sx - 0.5, 0, 1.0 / sy, 0.5 / sy - 0.5};
  const cv::Matx23d out_to_ct =
      invert_affine(similarity_matrix(ct_to_rgb, image_centre(ct_hu.size()), image_centre(grid)));
  cv::Mat ct32, ct_small;
  ct_hu.convertTo(ct32, CV_32F);
  cv::warpAffine(ct32, ct_small, cv::Mat(compose_affine(out_to_ct, small_to_out)), out.size(),
                 cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT, cv::Scalar(-1024));
  const cv::Mat body = ct_small > hu_threshold;
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(body, contours, cv::RETR_LIST, cv::CHAIN_APPROX_NONE);
  cv::drawContours(out, contours, -1, cv::Scalar(255, 0, 255), 1, cv::LINE_8);
  return out;
}

std::vector<int> abrupt_anchor_changes(const std::vector<std::optional<AnchorEstimate>>& anchors) {
  std::vector<int> out;
  const AnchorEstimate* previous = nullptr;
  for (std::size_t k = 0; k < anchors.size(); ++k) {
    if (!anchors[k]) continue;
    const AnchorEstimate& a = *anchors[k];
    if (previous && (std::abs(a.parts_ct - previous->parts_ct) >= kAbruptParts ||
                     std::abs(a.parts_colour - previous->parts_colour) >= kAbruptParts ||
                     std::abs(a.confidence - previous->confidence) >= kAbruptConfidence))
      out.push_back(int(k));
    previous = &a;
  }
  return out;
}

cv::Mat plot_transforms(const std::vector<SliceTransform>& slices,
                        const std::vector<std::optional<AnchorEstimate>>& anchors,
                        const std::vector<SliceOverride>& overrides, const std::string& title) {
  const int width = 1200, panel_h = 270, top = 40, left = 80, right = 20;
  const int height = top + 3 * panel_h + 20;
  cv::Mat img(height, width, CV_8UC3, cv::Scalar(255, 255, 255));
  cv::putText(img, title, {left, 26}, cv::FONT_HERSHEY_SIMPLEX, 0.6, cv::Scalar(0, 0, 0), 1,
              cv::LINE_AA);
  const int n = int(slices.size());
  if (n == 0) return img;
  const char* names[3] = {"dx px", "dy px", "rotation deg"};
  const std::vector<int> abrupt = abrupt_anchor_changes(anchors);
  auto value = [](const SliceTransform& s, int c) {
    return c == 0 ? s.rigid.dx_px : c == 1 ? s.rigid.dy_px : s.rigid.rotation_deg;
  };
  auto anchor_value = [](const AnchorEstimate& a, int c) {
    return c == 0 ? a.transform.dx_px : c == 1 ? a.transform.dy_px : a.transform.rotation_deg;
  };
  for (int c = 0; c < 3; ++c) {
    const int y0 = top + c * panel_h + 10, y1 = top + (c + 1) * panel_h - 20;
    double lo = 1e300, hi = -1e300;
    for (const auto& s : slices)
      lo = std::min(lo, value(s, c)), hi = std::max(hi, value(s, c));
    for (const auto& a : anchors)
      if (a && a->ok && a->confidence > 0.05)
        lo = std::min(lo, anchor_value(*a, c)), hi = std::max(hi, anchor_value(*a, c));
    const double span = std::max(hi - lo, c == 2 ? 0.2 : 2.0);
    const double mid = 0.5 * (hi + lo);
    lo = mid - 0.55 * span, hi = mid + 0.55 * span;
    auto px = [&](double k) {
      return int(std::lround(left + (width - left - right) * (n > 1 ? k / (n - 1) : 0.5)));
    };
    auto py = [&](double v) { return int(std::lround(y1 - (y1 - y0) * (v - lo) / (hi - lo))); };
    cv::rectangle(img, {left, y0}, {width - right, y1}, cv::Scalar(160, 160, 160), 1);
    char label[64];
    for (double v : {lo, mid, hi}) {
      std::snprintf(label, sizeof label, "%.2f", v);
      cv::putText(img, label, {4, py(v) + 4}, cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(60, 60, 60),
                  1, cv::LINE_AA);
    }
    cv::putText(img, names[c], {left + 6, y0 + 16}, cv::FONT_HERSHEY_SIMPLEX, 0.5,
                cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
    for (const auto& s : slices)
      if (s.jump)
        cv::line(img, {px(s.index - 0.5), y0}, {px(s.index - 0.5), y1}, cv::Scalar(220, 0, 0), 1);
    for (int k : abrupt)
      cv::line(img, {px(k), y1 - 8}, {px(k), y1}, cv::Scalar(220, 0, 220), 2);
    for (const auto& o : overrides)
      cv::drawMarker(img, {px(o.index), y0 + 6}, cv::Scalar(255, 140, 0), cv::MARKER_TRIANGLE_DOWN,
                     10, 2);
    // Anchors: dots, filled and darker with confidence; hollow where confidence < 0.2.
    for (std::size_t k = 0; k < anchors.size() && int(k) < n; ++k) {
      const auto& a = anchors[k];
      if (!a || !a->ok) continue;
      const int shade = int(200 - 170 * a->confidence);
      const cv::Point p(px(double(k)), std::clamp(py(anchor_value(*a, c)), y0, y1));
      cv::circle(img, p, 3, cv::Scalar(shade, shade, 255), a->confidence < 0.2 ? 1 : -1,
                 cv::LINE_AA);
    }
    for (int k = 1; k < n; ++k)
      cv::line(img, {px(k - 1), py(value(slices[std::size_t(k - 1)], c))},
               {px(k), py(value(slices[std::size_t(k)], c))}, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  }
  cv::putText(img,
              "line: solved transform; blue dots: CT anchors (darker = more confident, hollow < "
              "0.2); red lines: jumps; orange marks: overrides; magenta ticks: part count or "
              "confidence changes abruptly",
              {left, height - 6}, cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(0, 0, 0), 1,
              cv::LINE_AA);
  return img;
}

}  // namespace vispack::pipeline

// Body masks from CT with colour refinement. See mask.h for the steps.
#include "vispack/pipeline/mask.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/pipeline/rigid.h"

namespace vispack::pipeline {
namespace {

cv::Mat disc(int radius) {
  return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
}

// The output-grid rectangle the CT mask can touch, grown by `margin` and clipped to `size`.
cv::Rect mapped_bounds(const cv::Mat& ct_mask, const cv::Matx23d& out_to_ct, cv::Size size,
                       int margin) {
  cv::Rect box = cv::boundingRect(ct_mask);
  if (box.empty()) return {};
  const cv::Matx23d ct_to_out = invert_affine(out_to_ct);
  double x0 = 1e300, y0 = 1e300, x1 = -1e300, y1 = -1e300;
  for (double x : {box.x - 1.0, box.x + box.width + 0.0}) {
    for (double y : {box.y - 1.0, box.y + box.height + 0.0}) {
      const double qx = ct_to_out(0, 0) * x + ct_to_out(0, 1) * y + ct_to_out(0, 2);
      const double qy = ct_to_out(1, 0) * x + ct_to_out(1, 1) * y + ct_to_out(1, 2);
      x0 = std::min(x0, qx), x1 = std::max(x1, qx), y0 = std::min(y0, qy), y1 = std::max(y1, qy);
    }
  }
  cv::Rect r(int(std::floor(x0)) - margin, int(std::floor(y0)) - margin,
             int(std::ceil(x1 - x0)) + 2 * margin + 2, int(std::ceil(y1 - y0)) + 2 * margin + 2);
  return r & cv::Rect(0, 0, size.width, size.height);
}

cv::Mat to_hu_float(const cv::Mat& ct_hu) {
  if (ct_hu.type() == CV_32FC1) return ct_hu;
  if (ct_hu.channels() != 1) throw InputError(cat("CT slice has ", ct_hu.channels(), " channels"));
  cv::Mat f;
  ct_hu.convertTo(f, CV_32F);
  return f;
}

void check_rgb(const cv::Mat& rgb, const char* what) {
  if (rgb.empty() || rgb.type() != CV_8UC3)
    throw InputError(cat(what, ": expected an 8-bit RGB slice, got type ", rgb.type()));
}

}  // namespace

cv::Mat largest_component(const cv::Mat& mask) {
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8, CV_32S);
  cv::Mat out = cv::Mat::zeros(mask.size(), CV_8UC1);
  if (n <= 1) return out;
  int best = 1;
  for (int i = 2; i < n; ++i)
    if (stats.at<int>(i, cv::CC_STAT_AREA) > stats.at<int>(best, cv::CC_STAT_AREA)) best = i;
  if (n == 2) return mask > 0;
  return labels == best;
}

cv::Mat fill_holes(const cv::Mat& mask) {
  // Flood the background from a 1-pixel frame around the image; what stays 0 is a hole.
  cv::Mat padded;
  cv::copyMakeBorder(mask > 0, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::floodFill(padded, cv::Point(0, 0), cv::Scalar(128), nullptr, cv::Scalar(0), cv::Scalar(0), 4);
  cv::Mat inner = padded(cv::Rect(1, 1, mask.cols, mask.rows));
  return inner != 128;
}

cv::Mat open_disc(const cv::Mat& mask, int radius) {
  if (radius <= 0) return mask.clone();
  cv::Mat out;
  cv::morphologyEx(mask, out, cv::MORPH_OPEN, disc(radius));
  return out;
}

cv::Mat ct_body_mask(const cv::Mat& ct_hu, double hu_threshold) {
  cv::Mat hu = to_hu_float(ct_hu);
  cv::Mat raw = hu > hu_threshold;
  // The opening cuts thin bridges (head-holder, table); the largest component is the body.
  cv::Mat body = largest_component(open_disc(raw, kCtDetachPx));
  if (cv::countNonZero(body) == 0) return body;
  // Grow back what the opening shaved off the body's own edge, only within its radius + 1.
  cv::Mat grown;
  cv::dilate(body, grown,
             cv::getStructuringElement(cv::MORPH_ELLIPSE,
                                       cv::Size(2 * kCtDetachPx + 3, 2 * kCtDetachPx + 3)));
  return fill_holes(largest_component(raw & grown));
}

cv::Vec3f estimate_gel_colour(const cv::Mat& rgb) {
  check_rgb(rgb, "estimate_gel_colour");
  const int band = std::max(1, std::min({4, rgb.cols / 4, rgb.rows / 4}));
  std::vector<int> channel[3];
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3b* row = rgb.ptr<cv::Vec3b>(y);
    const bool edge_row = y < band || y >= rgb.rows - band;
    for (int x = 0; x < rgb.cols; ++x) {
      if (!edge_row && x >= band && x < rgb.cols - band) {
        x = rgb.cols - band - 1;
        continue;
      }
      for (int c = 0; c < 3; ++c)
        channel[c].push_back(row[x][c]);
    }
  }
  cv::Vec3f gel;
  for (int c = 0; c < 3; ++c) {
    auto mid = channel[c].begin() + channel[c].size() / 2;
    std::nth_element(channel[c].begin(), mid, channel[c].end());
    gel[c] = float(*mid);
  }
  return gel;
}

cv::Mat non_gel(const cv::Mat& rgb, const cv::Vec3f& gel, double distance) {
  check_rgb(rgb, "non_gel");
  cv::Mat out(rgb.size(), CV_8UC1);
  const int g0 = int(std::lround(gel[0])), g1 = int(std::lround(gel[1])),
            g2 = int(std::lround(gel[2]));
  const int limit = int(std::floor(distance * distance));
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3b* in = rgb.ptr<cv::Vec3b>(y);
    std::uint8_t* o = out.ptr<std::uint8_t>(y);
    for (int x = 0; x < rgb.cols; ++x) {
      const int a = in[x][0] - g0, b = in[x][1] - g1, c = in[x][2] - g2;
      o[x] = (a * a + b * b + c * c > limit) ? 255 : 0;
    }
  }
  return out;
}

cv::Mat colour_body_mask(const cv::Mat& rgb, const cv::Vec3f& gel, double distance,
                         int opening_px) {
  return fill_holes(largest_component(open_disc(non_gel(rgb, gel, distance), opening_px)));
}

cv::Mat remove_edge_gel(const cv::Mat& mask, const cv::Mat& rgb, const cv::Vec3f& gel,
                        double distance) {
  check_rgb(rgb, "remove_edge_gel");
  if (mask.size() != rgb.size()) throw Error("remove_edge_gel: mask and slice differ in size");
  // Candidate = outside ∪ (inside ∧ gel-coloured); flood it from a frame of outside pixels.
  cv::Mat gelish = non_gel(rgb, gel, distance) == 0;
  cv::Mat candidate = (mask == 0) | gelish;
  cv::Mat padded;
  cv::copyMakeBorder(candidate, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(255));
  cv::floodFill(padded, cv::Point(0, 0), cv::Scalar(128), nullptr, cv::Scalar(0), cv::Scalar(0), 4);
  cv::Mat reached = padded(cv::Rect(1, 1, mask.cols, mask.rows)) == 128;
  cv::Mat out = mask.clone();
  out.setTo(0, reached);
  return out;
}

cv::Mat resample_ct(const cv::Mat& ct_hu, const cv::Matx23d& out_to_ct, cv::Size size) {
  cv::Mat out;
  cv::warpAffine(to_hu_float(ct_hu), out, cv::Mat(out_to_ct), size,
                 cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT, cv::Scalar(-1024));
  return out;
}

cv::Mat resample_mask(const cv::Mat& mask, const cv::Matx23d& out_to_ct, cv::Size size) {
  cv::Mat out;
  cv::warpAffine(mask, out, cv::Mat(out_to_ct), size, cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                 cv::BORDER_CONSTANT, cv::Scalar(0));
  return out >= 128;
}

cv::Mat encode_hu16(const cv::Mat& hu) {
  cv::Mat out;
  to_hu_float(hu).convertTo(out, CV_16U, 1.0, 32768.0);  // saturating: clamps to 0..65535
  return out;
}

cv::Mat draw_mask_overlay(const cv::Mat& rgb, const cv::Mat& mask) {
  check_rgb(rgb, "draw_mask_overlay");
  cv::Mat eroded;
  cv::erode(mask, eroded, cv::Mat(), cv::Point(-1, -1), 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::Mat outline = mask & ~eroded;
  cv::Mat out = rgb.clone();
  out.setTo(cv::Scalar(255, 255, 0), outline);
  return out;
}

MaskSlice compute_mask(const cv::Mat& rgb, const cv::Mat* ct_hu, const cv::Matx23d& out_to_ct,
                       const MaskOptions& options) {
  check_rgb(rgb, "compute_mask");
  MaskSlice result;
  result.gel = options.gel_colour
                   ? cv::Vec3f(float((*options.gel_colour)[0]), float((*options.gel_colour)[1]),
                               float((*options.gel_colour)[2]))
                   : estimate_gel_colour(rgb);
  const cv::Size size = rgb.size();
  if (!ct_hu) {
    result.mask = colour_body_mask(rgb, result.gel, options.gel_distance, options.opening_px);
  } else {
    cv::Mat ct_mask = ct_body_mask(*ct_hu, options.hu_threshold);
    result.mask = cv::Mat::zeros(size, CV_8UC1);
    // Work inside the rectangle the CT body can reach (plus a frame of outside pixels).
    const int margin = options.opening_px + 4;
    const cv::Rect roi = mapped_bounds(ct_mask, out_to_ct, size, margin);
    if (!roi.empty()) {
      const cv::Matx23d shift{1, 0, double(roi.x), 0, 1, double(roi.y)};
      cv::Mat m = resample_mask(ct_mask, compose_affine(out_to_ct, shift), roi.size());
      const cv::Mat rgb_roi = rgb(roi);
      if (options.refine_gel) m = remove_edge_gel(m, rgb_roi, result.gel, options.gel_distance);
      m = fill_holes(largest_component(open_disc(m, options.opening_px)));
      m.copyTo(result.mask(roi));
    }
  }
  result.coverage = double(cv::countNonZero(result.mask)) / double(size.area());
  return result;
}

}  // namespace vispack::pipeline

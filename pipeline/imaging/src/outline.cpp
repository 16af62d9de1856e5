// Body and gel outlines from CT and colour slices. See outline.h.
#include "vispack/pipeline/imaging/outline.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"

namespace vispack::pipeline {
namespace {

cv::Mat disc(int radius) {
  return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
}

}  // namespace

cv::Mat ct_hu_float(const cv::Mat& ct_hu) {
  if (ct_hu.type() == CV_32FC1) return ct_hu;
  if (ct_hu.channels() != 1) throw InputError(cat("CT slice has ", ct_hu.channels(), " channels"));
  cv::Mat f;
  ct_hu.convertTo(f, CV_32F);
  return f;
}

void require_rgb_slice(const cv::Mat& rgb, const char* what) {
  if (rgb.empty() || rgb.type() != CV_8UC3)
    throw InputError(cat(what, ": expected an 8-bit RGB slice, got type ", rgb.type()));
}

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
  cv::Mat hu = ct_hu_float(ct_hu);
  // Holes filled first: a cavity near the body's edge (a sinus, an airway) leaves only a thin
  // band of tissue between it and the outside, which the opening below would cut off with the
  // holder (at the ends of the stack, where the body is a few CT pixels across, half the body).
  cv::Mat raw = fill_holes(hu > hu_threshold);
  // The opening cuts thin bridges (head-holder, table); the largest component is the body.
  cv::Mat body = largest_component(open_disc(raw, kCtDetachPx));
  const cv::Rect bounds = cv::boundingRect(body);
  if (bounds.empty()) return body;
  // Grow back what the opening shaved off the body's own edge, only within its radius + 1. All
  // of it lies within the body's bounding box grown by that radius; one more pixel of background
  // around it lets fill_holes work on the box alone (same result, a fraction of the pixels).
  const int reach = kCtDetachPx + 1, m = reach + 1;
  const cv::Rect box =
      cv::Rect(bounds.x - m, bounds.y - m, bounds.width + 2 * m, bounds.height + 2 * m) &
      cv::Rect(0, 0, body.cols, body.rows);
  cv::Mat grown;
  cv::dilate(body(box), grown,
             cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * reach + 1, 2 * reach + 1)));
  cv::Mat out = cv::Mat::zeros(body.size(), CV_8UC1);
  fill_holes(largest_component(raw(box) & grown)).copyTo(out(box));
  return out;
}

cv::Vec3f estimate_gel_colour(const cv::Mat& rgb) {
  require_rgb_slice(rgb, "estimate_gel_colour");
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
  require_rgb_slice(rgb, "non_gel");
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

}  // namespace vispack::pipeline

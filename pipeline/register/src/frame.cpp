// Frame preparation: grey levels, fiducials, pixel hash, black flag, and the colour level of
// the CT anchor. See register/frame.h.
#include "vispack/pipeline/register/frame.h"

#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/math_constants.h"
#include "vispack/pipeline/imaging/outline.h"

namespace vispack::pipeline {
namespace {

constexpr int kCoarseEdge = 256;             // longer edge of the coarse level, pixels
constexpr int kFiducialColourDistance = 40;  // RGB distance from the gel of a fiducial blob

cv::Mat to_grey_float(const cv::Mat& slice) {
  if (slice.empty()) throw InputError("prepare_frame: empty slice");
  cv::Mat grey;
  if (slice.channels() == 3) {
    cv::cvtColor(slice, grey, cv::COLOR_RGB2GRAY);
  } else if (slice.channels() == 1) {
    grey = slice;
  } else if (slice.channels() == 4) {
    cv::cvtColor(slice, grey, cv::COLOR_RGBA2GRAY);
  } else {
    throw InputError(cat("prepare_frame: unsupported channel count ", slice.channels()));
  }
  cv::Mat out;
  const double scale = grey.depth() == CV_16U ? 255.0 / 65535.0 : 1.0;
  grey.convertTo(out, CV_32F, scale);
  return out;
}

cv::Mat resize_to(const cv::Mat& image, double scale) {
  if (scale >= 0.999) return image;
  cv::Size size(std::max(8, int(std::lround(image.cols * scale))),
                std::max(8, int(std::lround(image.rows * scale))));
  cv::Mat out;
  cv::resize(image, out, size, 0, 0, cv::INTER_AREA);
  return out;
}

std::uint64_t hash_pixels(const cv::Mat& m) {
  if (m.isContinuous()) return xxh64(m.data, m.total() * m.elemSize());
  std::uint64_t h = 0;
  for (int y = 0; y < m.rows; ++y)
    h = xxh64(m.ptr(y), m.cols * m.elemSize(), h);
  return h;
}

}  // namespace

std::vector<cv::Point2d> find_fiducials(const cv::Mat& rgb) {
  std::vector<cv::Point2d> out;
  if (rgb.empty() || rgb.type() != CV_8UC3 || rgb.cols < 16 || rgb.rows < 16) return out;
  const cv::Vec3f gel = estimate_gel_colour(rgb);
  const cv::Vec3d gel_d(gel[0], gel[1], gel[2]);
  cv::Mat coarse = rgb;
  const double want = std::min(1.0, double(kCoarseEdge) / std::max(rgb.cols, rgb.rows));
  if (want < 0.999) cv::resize(rgb, coarse, cv::Size(), want, want, cv::INTER_AREA);
  const double sx = double(coarse.cols) / rgb.cols, sy = double(coarse.rows) / rgb.rows;
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(non_gel(coarse, gel, kFiducialColourDistance),
                                                 labels, stats, centroids, 8, CV_32S);
  int body = 0;
  for (int i = 1; i < n; ++i)
    if (body == 0 || stats.at<int>(i, cv::CC_STAT_AREA) > stats.at<int>(body, cv::CC_STAT_AREA))
      body = i;
  for (int i = 1; i < n; ++i) {
    if (i == body) continue;
    const int x = stats.at<int>(i, cv::CC_STAT_LEFT), y = stats.at<int>(i, cv::CC_STAT_TOP);
    const int w = stats.at<int>(i, cv::CC_STAT_WIDTH), h = stats.at<int>(i, cv::CC_STAT_HEIGHT);
    const int area = stats.at<int>(i, cv::CC_STAT_AREA);
    if (area < 12 || x < 2 || y < 2 || x + w > coarse.cols - 2 || y + h > coarse.rows - 2) continue;
    const double r = 0.5 * std::max(w, h);
    if (area < 0.6 * kPi * r * r || std::max(w, h) > 1.6 * std::min(w, h)) continue;
    // The blob's window on the full-resolution slice (grown by half its radius, >= 3 px).
    const double g = std::max(3.0, 0.5 * r);
    const int x0 = int(std::floor((x - g + 0.5) / sx - 0.5));
    const int y0 = int(std::floor((y - g + 0.5) / sy - 0.5));
    const int x1 = int(std::ceil((x + w + g + 0.5) / sx - 0.5));
    const int y1 = int(std::ceil((y + h + g + 0.5) / sy - 0.5));
    if (x0 < 1 || y0 < 1 || x1 > rgb.cols - 1 || y1 > rgb.rows - 1) continue;
    const cv::Mat roi = rgb(cv::Rect(x0, y0, x1 - x0, y1 - y0));
    // Blob colour: the mean of the window's non-gel pixels.
    const int limit = kFiducialColourDistance * kFiducialColourDistance;
    cv::Vec3d sum(0, 0, 0);
    int count = 0;
    for (int yy = 0; yy < roi.rows; ++yy) {
      const cv::Vec3b* row = roi.ptr<cv::Vec3b>(yy);
      for (int xx = 0; xx < roi.cols; ++xx) {
        const cv::Vec3d c(row[xx][0], row[xx][1], row[xx][2]);
        const cv::Vec3d dlt = c - gel_d;
        if (dlt.dot(dlt) > limit) sum += c, ++count;
      }
    }
    if (count == 0) continue;
    const cv::Vec3d axis = sum / count - gel_d;
    const double a2 = axis.dot(axis);
    if (!(a2 > 1.0)) continue;
    // Coverage-weighted centroid: coverage 0.15 → 0 … 1.1 → 1 along the gel→blob axis.
    double sw = 0, swx = 0, swy = 0;
    for (int yy = 0; yy < roi.rows; ++yy) {
      const cv::Vec3b* row = roi.ptr<cv::Vec3b>(yy);
      for (int xx = 0; xx < roi.cols; ++xx) {
        const cv::Vec3d c(row[xx][0], row[xx][1], row[xx][2]);
        const double cover = (c - gel_d).dot(axis) / a2;
        const double wt = std::clamp((cover - 0.15) / 0.95, 0.0, 1.0);
        sw += wt, swx += wt * (x0 + xx), swy += wt * (y0 + yy);
      }
    }
    if (sw > 0) out.emplace_back(swx / sw, swy / sw);
  }
  std::sort(out.begin(), out.end(), [](const cv::Point2d& a, const cv::Point2d& b) {
    return a.y != b.y ? a.y < b.y : a.x < b.x;
  });
  return out;
}

RegisterFrame prepare_frame(const cv::Mat& slice, const RegisterOptions& options,
                            double anchor_scale) {
  RegisterFrame f;
  f.full_size = slice.size();
  f.pixel_hash = hash_pixels(slice);
  cv::Mat grey = to_grey_float(slice);
  const double fine_scale = std::clamp(options.ecc_scale, 0.05, 1.0);
  f.fine_scale = fine_scale >= 0.999 ? 1.0 : fine_scale;
  f.fine = resize_to(grey, f.fine_scale);
  cv::Scalar mean, stddev;
  cv::meanStdDev(f.fine, mean, stddev);
  f.black = mean[0] < 4.0 && stddev[0] < 2.0;
  const double coarse = std::min(1.0, double(kCoarseEdge) / std::max(slice.cols, slice.rows));
  if (coarse >= f.fine_scale * 0.999) {
    f.coarse = f.fine;
    f.coarse_scale = f.fine_scale;
  } else {
    f.coarse_scale = coarse;
    f.coarse = resize_to(f.fine, coarse / f.fine_scale);
    // The actual size ratio (rounding) defines the scale used for coordinates.
    f.coarse_scale = double(f.coarse.cols) / slice.cols;
  }
  if (f.fine_scale < 1.0) f.fine_scale = double(f.fine.cols) / slice.cols;
  if (f.fine_scale >= 3.0 * f.coarse_scale) {
    f.middle = resize_to(f.fine, 0.5);
    f.middle_scale = double(f.middle.cols) / slice.cols;
    cv::GaussianBlur(f.middle, f.middle, cv::Size(5, 5), 0, 0);
  }
  // The 5×5 Gaussian that ECC applies to both images of every pair, done once per frame
  // (a frame takes part in up to four pairs).
  const bool shared = f.coarse.data == f.fine.data;
  cv::GaussianBlur(f.fine, f.fine, cv::Size(5, 5), 0, 0);
  if (shared) {
    f.coarse = f.fine;
  } else {
    cv::GaussianBlur(f.coarse, f.coarse, cv::Size(5, 5), 0, 0);
  }
  if (anchor_scale > 0.0) {
    cv::Mat colour;
    if (slice.channels() == 3) {
      colour = slice;
    } else if (slice.channels() == 1) {
      cv::cvtColor(slice, colour, cv::COLOR_GRAY2RGB);
    } else {
      cv::cvtColor(slice, colour, cv::COLOR_RGBA2RGB);
    }
    cv::Mat small;
    const double a = std::min(1.0, anchor_scale);
    const cv::Size size(std::max(8, int(std::lround(slice.cols * a))),
                        std::max(8, int(std::lround(slice.rows * a))));
    if (size == colour.size()) {
      small = colour;
    } else {
      cv::resize(colour, small, size, 0, 0, cv::INTER_AREA);
    }
    small.convertTo(f.anchor_colour, CV_32F,
                    colour.depth() == CV_16U ? 1.0 / 65535.0 : 1.0 / 255.0);
    f.anchor_scale = double(size.width) / slice.cols;
  }
  if (!f.black && options.method != "none") {
    if (slice.type() == CV_8UC3) {
      f.fiducials = find_fiducials(slice);
    } else if (slice.type() == CV_16UC3) {
      cv::Mat rgb8;
      slice.convertTo(rgb8, CV_8U, 255.0 / 65535.0);
      f.fiducials = find_fiducials(rgb8);
    }
  }
  return f;
}

}  // namespace vispack::pipeline

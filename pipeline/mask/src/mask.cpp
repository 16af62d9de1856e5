// Body masks from CT with colour refinement. See mask.h for the steps.
#include "vispack/pipeline/mask/mask.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/pipeline/imaging/transforms.h"

namespace vispack::pipeline {
namespace {

// Depth (output pixels) of the edge band in which the gel refinement may remove pixels.
constexpr double kGelBandPx = 12.0;

cv::Mat disc(int radius) {
  return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
}

// The edge levels image (CV_8UC1, CT resolution) carried onto the output grid by one linear
// warp. Outside the body 0; along the body's edge (pixels 8-adjacent to the other side) the HU
// mapped linearly, kLevelEdge at `level` and ±kLevelEdge per kLevelSpanHu, clamped so that body
// pixels stay ≥ kLevelEdge and the others below it; deeper body pixels kLevelBand, and those
// more than band_ct CT pixels deep kLevelCore. After the warp: ≥ kLevelEdge is body (the
// linearly interpolated HU crosses `level` where the value crosses kLevelEdge), and body below
// kLevelBandEnd lies in the edge band.
constexpr int kLevelEdge = 85, kLevelBand = 200, kLevelCore = 255, kLevelBandEnd = 228;
constexpr double kLevelSpanHu = 500.0;

cv::Mat edge_levels(const cv::Mat& body, const cv::Mat& hu, double level, int band_ct) {
  cv::Mat levels = cv::Mat::zeros(body.size(), CV_8UC1);
  // Only the body's bounding box grown by 2 (its outside neighbours, and zeros for the erosions
  // to see) is touched.
  const cv::Rect bounds = cv::boundingRect(body);
  if (bounds.empty()) return levels;
  const cv::Rect box = cv::Rect(bounds.x - 2, bounds.y - 2, bounds.width + 4, bounds.height + 4) &
                       cv::Rect(0, 0, body.cols, body.rows);
  const cv::Mat b = body(box);
  cv::Mat inner, outer, core;
  cv::erode(b, inner, cv::Mat(), cv::Point(-1, -1), 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::dilate(b, outer, cv::Mat());
  cv::erode(b, core, disc(band_ct), cv::Point(-1, -1), 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  const double gain = kLevelEdge / kLevelSpanHu;
  for (int y = 0; y < box.height; ++y) {
    const std::uint8_t* bp = b.ptr<std::uint8_t>(y);
    const std::uint8_t* in = inner.ptr<std::uint8_t>(y);
    const std::uint8_t* out = outer.ptr<std::uint8_t>(y);
    const std::uint8_t* c = core.ptr<std::uint8_t>(y);
    const float* h = hu.ptr<float>(box.y + y) + box.x;
    std::uint8_t* l = levels.ptr<std::uint8_t>(box.y + y) + box.x;
    for (int x = 0; x < box.width; ++x) {
      if (c[x]) {
        l[x] = kLevelCore;
      } else if (in[x]) {
        l[x] = kLevelBand;
      } else if (out[x]) {
        const double v = kLevelEdge + (double(h[x]) - level) * gain;
        l[x] = bp[x] ? std::uint8_t(std::clamp(v, double(kLevelEdge + 1), double(2 * kLevelEdge)))
                     : std::uint8_t(std::clamp(v, 0.0, double(kLevelEdge - 1)));
      }
    }
  }
  return levels;
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

}  // namespace

cv::Mat remove_edge_gel(const cv::Mat& mask, const cv::Mat& rgb, const cv::Vec3f& gel,
                        double distance, const cv::Mat& band, cv::Rect* removed) {
  require_rgb_slice(rgb, "remove_edge_gel");
  if (mask.size() != rgb.size() || mask.type() != CV_8UC1)
    throw Error("remove_edge_gel: mask and slice differ in size (or the mask is not 8-bit)");
  if (!band.empty() && (band.size() != mask.size() || band.type() != CV_8UC1))
    throw Error("remove_edge_gel: band and mask differ in size");
  if (removed) *removed = cv::Rect();
  // The squared colour distance to the gel of every pixel that may be removed (mask ∧ band).
  const float g0 = gel[0], g1 = gel[1], g2 = gel[2];
  const float limit = float(distance * distance);
  std::vector<std::pair<int, float>> examined;  // (offset y·cols + x, squared distance)
  std::vector<float> tissue;                    // squared distances of clearly non-gel pixels
  for (int y = 0; y < mask.rows; ++y) {
    const std::uint8_t* m = mask.ptr<std::uint8_t>(y);
    const std::uint8_t* b = band.empty() ? m : band.ptr<std::uint8_t>(y);
    const cv::Vec3b* c = rgb.ptr<cv::Vec3b>(y);
    for (int x = 0; x < mask.cols; ++x) {
      if (!m[x] || !b[x]) continue;
      const float a = c[x][0] - g0, bb = c[x][1] - g1, cc = c[x][2] - g2;
      const float d2 = a * a + bb * bb + cc * cc;
      examined.emplace_back(y * mask.cols + x, d2);
      if (d2 > limit) tissue.push_back(d2);
    }
  }
  // Gel-coloured: closer than `distance`, or than half the median tissue distance (an edge
  // pixel less than half covered by tissue; tissue showing through the translucent gel next to
  // the body would otherwise count as body).
  float level = limit;
  if (!tissue.empty()) {
    auto mid = tissue.begin() + tissue.size() / 2;
    std::nth_element(tissue.begin(), mid, tissue.end());
    level = std::max(limit, 0.25f * *mid);  // (half the distance)²
  }
  // Gel-coloured examined pixels (255); those connected (4-neighbours) to the outside of the
  // mask are flooded to 128 from seeds next to the outside or the image border.
  cv::Mat gelish = cv::Mat::zeros(mask.size(), CV_8UC1);
  std::uint8_t* gp = gelish.data;
  for (const auto& e : examined)
    if (e.second < level) gp[e.first] = 255;
  const int w = mask.cols, h = mask.rows;
  auto outside = [&](int x, int y) {
    return x < 0 || y < 0 || x >= w || y >= h || mask.at<std::uint8_t>(y, x) == 0;
  };
  // A breadth-first fill over the gel-coloured pixels only (cv::floodFill clears a mask of the
  // whole image on every call: far too slow for many small seeds).
  std::vector<int> queue;
  for (const auto& e : examined) {
    if (gp[e.first] != 255) continue;
    const int x = e.first % w, y = e.first / w;
    if (!(outside(x - 1, y) || outside(x + 1, y) || outside(x, y - 1) || outside(x, y + 1)))
      continue;
    gp[e.first] = 128;
    queue.assign(1, e.first);
    while (!queue.empty()) {
      const int o = queue.back();
      queue.pop_back();
      const int ox = o % w, oy = o / w;
      if (ox > 0 && gp[o - 1] == 255) gp[o - 1] = 128, queue.push_back(o - 1);
      if (ox + 1 < w && gp[o + 1] == 255) gp[o + 1] = 128, queue.push_back(o + 1);
      if (oy > 0 && gp[o - w] == 255) gp[o - w] = 128, queue.push_back(o - w);
      if (oy + 1 < h && gp[o + w] == 255) gp[o + w] = 128, queue.push_back(o + w);
    }
  }
  cv::Mat out = mask.clone();
  int x0 = w, y0 = h, x1 = -1, y1 = -1;
  for (const auto& e : examined) {
    if (gp[e.first] != 128) continue;
    out.data[e.first] = 0;
    const int x = e.first % w, y = e.first / w;
    x0 = std::min(x0, x), x1 = std::max(x1, x), y0 = std::min(y0, y), y1 = std::max(y1, y);
  }
  if (removed && x1 >= 0) *removed = cv::Rect(x0, y0, x1 - x0 + 1, y1 - y0 + 1);
  return out;
}

cv::Mat draw_mask_overlay(const cv::Mat& rgb, const cv::Mat& mask) {
  require_rgb_slice(rgb, "draw_mask_overlay");
  cv::Mat eroded;
  cv::erode(mask, eroded, cv::Mat(), cv::Point(-1, -1), 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::Mat outline = mask & ~eroded;
  cv::Mat out = rgb.clone();
  out.setTo(cv::Scalar(255, 255, 0), outline);
  return out;
}

MaskSlice compute_mask(const cv::Mat& rgb, const cv::Mat* ct_hu, const cv::Matx23d& out_to_ct,
                       const MaskOptions& options, double pixel_mm2, const ZNeighbours* z) {
  require_rgb_slice(rgb, "compute_mask");
  if (!(pixel_mm2 > 0.0)) throw Error(cat("compute_mask: pixel area ", pixel_mm2, " mm²"));
  const double min_part_px = options.min_part_mm2 / pixel_mm2;  // output pixels
  MaskSlice result;
  result.gel = options.gel_colour
                   ? cv::Vec3f(float((*options.gel_colour)[0]), float((*options.gel_colour)[1]),
                               float((*options.gel_colour)[2]))
                   : estimate_gel_colour(rgb);
  const cv::Size size = rgb.size();
  if (!ct_hu) {
    result.mask = colour_body_mask(rgb, result.gel, options.gel_distance, options.opening_px,
                                   min_part_px, &result.parts);
    // The threshold keeps edge pixels barely covered by tissue (11–15 % too much body on the
    // anatomy phantom's tips): those less than half covered go (step 4's test, in its band).
    cv::Mat core;
    cv::erode(result.mask, core, disc(int(kGelBandPx)), cv::Point(-1, -1), 1, cv::BORDER_CONSTANT,
              cv::Scalar(0));
    result.mask =
        remove_edge_gel(result.mask, rgb, result.gel, options.gel_distance, result.mask & ~core);
  } else {
    const cv::Mat hu = ct_hu_float(*ct_hu);
    const double level = mask_edge_level_hu(options.hu_threshold);
    // CT pixels per output pixel (area): |det out_to_ct|.
    const double ct_per_out =
        std::abs(out_to_ct(0, 0) * out_to_ct(1, 1) - out_to_ct(0, 1) * out_to_ct(1, 0));
    cv::Mat ct_mask = ct_body_mask(hu, level, min_part_px * ct_per_out, &result.parts, z);
    result.mask = cv::Mat::zeros(size, CV_8UC1);
    // Work inside the rectangle the CT body can reach (plus a frame of outside pixels).
    const int margin = options.opening_px + 4;
    const cv::Rect roi = mapped_bounds(ct_mask, out_to_ct, size, margin);
    if (!roi.empty()) {
      const cv::Matx23d shift{1, 0, double(roi.x), 0, 1, double(roi.y)};
      const cv::Matx23d roi_to_ct = compose_affine(out_to_ct, shift);
      // Output pixels per CT pixel.
      const double scale = 1.0 / std::sqrt(std::abs(out_to_ct(0, 0) * out_to_ct(1, 1) -
                                                    out_to_ct(0, 1) * out_to_ct(1, 0)));
      const int band_ct = std::max(1, int(std::ceil(kGelBandPx / scale)));
      cv::Mat warped;
      cv::warpAffine(edge_levels(ct_mask, hu, level, band_ct), warped, cv::Mat(roi_to_ct),
                     roi.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT,
                     cv::Scalar(0));
      cv::Mat carried(roi.size(), CV_8UC1), band(roi.size(), CV_8UC1);
      for (int y = 0; y < roi.height; ++y) {
        const std::uint8_t* in = warped.ptr<std::uint8_t>(y);
        std::uint8_t* mo = carried.ptr<std::uint8_t>(y);
        std::uint8_t* bo = band.ptr<std::uint8_t>(y);
        for (int x = 0; x < roi.width; ++x) {
          mo[x] = in[x] >= kLevelEdge ? 255 : 0;
          bo[x] = (in[x] >= kLevelEdge && in[x] < kLevelBandEnd) ? 255 : 0;
        }
      }
      cv::Mat m;
      if (options.refine_gel) {
        cv::Rect removed;
        m = remove_edge_gel(carried, rgb(roi), result.gel, options.gel_distance, band, &removed);
        // Removing gel connected to the outside cannot open holes; the opening smooths the
        // new edge where something was removed (and only there).
        if (!removed.empty() && options.opening_px > 0) {
          const int g = options.opening_px + 1;
          const cv::Rect box = cv::Rect(removed.x - g, removed.y - g, removed.width + 2 * g,
                                        removed.height + 2 * g) &
                               cv::Rect(0, 0, roi.width, roi.height);
          cv::Mat opened;
          cv::morphologyEx(m(box), opened, cv::MORPH_OPEN, disc(options.opening_px),
                           cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
          opened.copyTo(m(box));
        }
      } else {
        // The CT mask's parts are decided (step 2): the opening may only shed debris.
        PartRule rule;
        rule.min_area_px = min_part_px;
        rule.max_elongation = 0.0;
        m = fill_holes(body_parts(open_disc(carried, options.opening_px), rule));
      }
      result.coverage = double(cv::countNonZero(m)) / double(size.area());
      m.copyTo(result.mask(roi));
    }
  }
  if (!ct_hu) result.coverage = double(cv::countNonZero(result.mask)) / double(size.area());
  return result;
}

}  // namespace vispack::pipeline

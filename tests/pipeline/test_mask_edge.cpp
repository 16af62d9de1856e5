// Where the body mask's edge lies, against analytic truth: head-like cross-sections (ellipses
// with a wavy outline, a scalp of skin and fat over bone, an air-filled notch) of 200 000 down to
// 500 output pixels, rendered with exact partial volume into a CT 2× coarser than the colour grid
// (area-weighted HU, Gaussian noise) and into colour slices (tissue in blue gel, area-weighted
// colour at the edge, the translucent gel tinted by the tissue next to the body). The true mask is
// the set of colour-grid pixels whose centre lies inside the outline; no code under test draws it.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "vispack/common/math_constants.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/imaging/ct_shape_blend.h"
#include "vispack/pipeline/imaging/outline.h"
#include "vispack/pipeline/mask/mask.h"

namespace vp = vispack::pipeline;

namespace {

// A head-like cross-section on the colour grid (pixel centres at integer coordinates).
struct Section {
  double cx = 0, cy = 0;                    // centre (colour-grid pixels)
  double a = 0, b = 0;                      // semi-axes (colour-grid pixels)
  double angle = 0;                         // radians
  double wobble = 0.06;                     // relative radius modulation (3rd and 5th harmonics)
  double notch_width = 0, notch_depth = 0;  // an air/gel notch cut in along +x (0: none)

  // Layer outlines inside the outer one (skin 0–2, fat 2–5, bone 5–11 px deep, brain): each
  // an ellipse with its own semi-axes (a, b) and the same centre, angle and modulation.
  double la[3] = {0, 0, 0}, lb[3] = {0, 0, 0};

  // Nesting depth of (x, y): 0 outside, 1 skin, 2 fat, 3 bone, 4 brain.
  int layer(double x, double y) const {
    if (a <= 0 || b <= 0) return 0;
    const double dx = x - cx, dy = y - cy;
    const double u = cos_ * dx + sin_ * dy, v = -sin_ * dx + cos_ * dy;
    if (notch_depth > 0 && u > a - notch_depth && std::abs(v) < notch_width / 2) return 0;
    // Angle t of (u/a, v/b); the radius modulation m(t) from Chebyshev forms of sin/cos.
    const double un = u / a, vn = v / b, rho = std::sqrt(un * un + vn * vn);
    const double ct = rho > 0 ? un / rho : 1.0, st = rho > 0 ? vn / rho : 0.0;
    const double s3 = st * (3 - 4 * st * st), c3 = ct * (4 * ct * ct - 3);
    const double c5 = ct * (16 * ct * ct * ct * ct - 20 * ct * ct + 5);
    const double m = 1.0 + wobble * (0.6 * (s3 * 0.921061 + c3 * 0.389418) + 0.4 * c5);
    const double m2 = m * m;
    if (un * un + vn * vn > m2) return 0;
    int depth = 1;
    for (int k = 0; k < 3; ++k) {
      if (la[k] <= 0 || lb[k] <= 0) break;
      if ((u * u) / (la[k] * la[k]) + (v * v) / (lb[k] * lb[k]) > m2) break;
      ++depth;
    }
    return depth;
  }
  void set_angle(double radians) {
    angle = radians, cos_ = std::cos(radians), sin_ = std::sin(radians);
  }
  double cos_ = 1.0, sin_ = 0.0;
};

constexpr float kLayerHu[5] = {-1000.f, 40.f, -90.f, 900.f, 35.f};

// Area-weighted coverage (0..1) and HU of `s` on the colour grid (8×8 samples per pixel where
// a pixel is not uniform), within `box`.
void rasterise(const Section& s, cv::Rect box, cv::Mat& cover, cv::Mat& hu) {
  constexpr int kSub = 8;
  for (int y = box.y; y < box.y + box.height; ++y) {
    for (int x = box.x; x < box.x + box.width; ++x) {
      const int centre = s.layer(x, y);
      bool uniform = true;
      for (double ox : {-0.5, 0.5})
        for (double oy : {-0.5, 0.5})
          uniform = uniform && s.layer(x + ox, y + oy) == centre;
      if (uniform) {
        cover.at<float>(y, x) = centre > 0 ? 1.f : 0.f;
        hu.at<float>(y, x) = kLayerHu[centre];
        continue;
      }
      double in = 0, sum = 0;
      for (int j = 0; j < kSub; ++j) {
        for (int i = 0; i < kSub; ++i) {
          const int l = s.layer(x - 0.5 + (i + 0.5) / kSub, y - 0.5 + (j + 0.5) / kSub);
          in += l > 0;
          sum += kLayerHu[l];
        }
      }
      cover.at<float>(y, x) = float(in / (kSub * kSub));
      hu.at<float>(y, x) = float(sum / (kSub * kSub));
    }
  }
}

// The cap of a head: an ellipsoid with semi-axes (a0, b0, z_top) whose cross-section at height z
// (colour pixels above the widest section) has semi-axes (a0, b0)·sqrt(1 − (z/z_top)²); the layers
// are ellipsoids shrunk by their depth (2, 5, 11 px), so near the top skin and fat lie over the
// skull as they do in a head, not beside it.
struct Head {
  double a0 = 300, b0 = 235, z_top = 260;
  double cx = 512, cy = 304, angle = 0.2;
  Section at(double z) const {
    auto f = [&](double d) {
      const double t = z / (z_top - d);
      return std::sqrt(std::max(0.0, 1.0 - t * t));
    };
    Section s;
    s.cx = cx, s.cy = cy, s.a = a0 * f(0), s.b = b0 * f(0);
    const double depth[3] = {2, 5, 11};
    for (int k = 0; k < 3; ++k)
      s.la[k] = (a0 - depth[k]) * f(depth[k]), s.lb[k] = (b0 - depth[k]) * f(depth[k]);
    s.set_angle(angle);
    if (s.a > 60) s.notch_width = 6, s.notch_depth = 18;  // an ear canal, nostril
    return s;
  }
  // Height at which the cross-section has `area` pixels.
  double z_for_area(double area) const {
    const double f2 = area / (vispack::kPi * a0 * b0);
    return z_top * std::sqrt(std::max(0.0, 1.0 - f2));
  }
};

struct Rendered {
  cv::Mat rgb;    // CV_8UC3 colour slice (output grid)
  cv::Mat ct;     // CV_32F HU
  cv::Mat truth;  // 0/255 on the output grid
  cv::Matx23d out_to_ct;
};

struct CtModel {
  cv::Size size{512, 304};      // CT matrix
  double scale = 2.0;           // colour pixels per CT pixel
  double rotation = 0.0;        // radians, CT → output
  cv::Point2d shift{0.0, 0.0};  // colour pixels
  double slab_px = 3.0;         // slice thickness in colour pixels (1.5 mm at 0.5 mm pixels)
  double psf_sigma = 0.6;       // in-plane blur, CT pixels
  double noise_hu = 15.0;       // Gaussian noise
  double grow_px = 0.0;         // the CT's cross-section drawn this much wider (semi-axes)
};

// Output slice at height z of `head` on a colour grid of `size`. CT pixel u lands on the output
// grid at q = c + scale·R(rotation)(u − c_ct) + shift (c, c_ct: the image centres); its HU is the
// exact area-weighted mean (8×8 samples where the pixel is not uniform) over the slab
// z ± slab_px/2 (6 planes), blurred by the PSF, plus noise.
Rendered render(const Head& head_in, double z, cv::Size size, const CtModel& model,
                std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> n01(0.f, 1.f);
  Rendered r;
  const cv::Point2d c((size.width - 1) / 2.0, (size.height - 1) / 2.0);
  const cv::Point2d cc((model.size.width - 1) / 2.0, (model.size.height - 1) / 2.0);
  const double co = std::cos(model.rotation), si = std::sin(model.rotation);
  auto to_out = [&](double ux, double uy) {
    const double dx = ux - cc.x, dy = uy - cc.y;
    return cv::Point2d(c.x + model.scale * (co * dx - si * dy) + model.shift.x,
                       c.y + model.scale * (si * dx + co * dy) + model.shift.y);
  };
  // Inverse: u = c_ct + R(−rotation)(q − c − shift) / scale.
  const double is = 1.0 / model.scale;
  r.out_to_ct = cv::Matx23d(is * co, is * si, 0, -is * si, is * co, 0);
  for (int k = 0; k < 2; ++k) {
    const double qx = -c.x - model.shift.x, qy = -c.y - model.shift.y;
    r.out_to_ct(k, 2) = (k == 0 ? cc.x : cc.y) + r.out_to_ct(k, 0) * qx + r.out_to_ct(k, 1) * qy;
  }
  // CT.
  r.ct = cv::Mat(model.size, CV_32F, cv::Scalar(0));
  const int planes = model.slab_px > 0 ? 6 : 1;
  constexpr int kSub = 8;
  for (int p = 0; p < planes; ++p) {
    const double zp = z + model.slab_px * ((p + 0.5) / planes - 0.5);
    Section s = head_in.at(zp);
    s.a += model.grow_px, s.b += model.grow_px;
    for (int k = 0; k < 3; ++k)
      if (s.la[k] > 0) s.la[k] += model.grow_px, s.lb[k] += model.grow_px;
    // CT pixels within the section's circumscribed circle (plus 2 px); all others are air.
    const double reach = (std::max(s.a, s.b) * 1.07 + 2) / model.scale + 2;
    const cv::Matx23d& m = r.out_to_ct;
    const double ucx = m(0, 0) * s.cx + m(0, 1) * s.cy + m(0, 2);
    const double ucy = m(1, 0) * s.cx + m(1, 1) * s.cy + m(1, 2);
    for (int v = 0; v < model.size.height; ++v) {
      for (int u = 0; u < model.size.width; ++u) {
        if (std::abs(u - ucx) > reach || std::abs(v - ucy) > reach) {
          r.ct.at<float>(v, u) += kLayerHu[0] / float(planes);
          continue;
        }
        const cv::Point2d q = to_out(u, v);
        const int centre = s.layer(q.x, q.y);
        bool uniform = true;
        for (double ox : {-0.5, 0.5}) {
          for (double oy : {-0.5, 0.5}) {
            const cv::Point2d e = to_out(u + ox, v + oy);
            uniform = uniform && s.layer(e.x, e.y) == centre;
          }
        }
        double hu = kLayerHu[centre];
        if (!uniform) {
          double sum = 0;
          for (int j = 0; j < kSub; ++j) {
            for (int i = 0; i < kSub; ++i) {
              const cv::Point2d e = to_out(u - 0.5 + (i + 0.5) / kSub, v - 0.5 + (j + 0.5) / kSub);
              sum += kLayerHu[s.layer(e.x, e.y)];
            }
          }
          hu = sum / (kSub * kSub);
        }
        r.ct.at<float>(v, u) += float(hu / planes);
      }
    }
  }
  if (model.psf_sigma > 0) cv::GaussianBlur(r.ct, r.ct, cv::Size(0, 0), model.psf_sigma);
  for (auto it = r.ct.begin<float>(); it != r.ct.end<float>(); ++it)
    *it += float(model.noise_hu) * n01(rng);
  // Colour slice and truth at z itself.
  const Section s = head_in.at(z);
  cv::Mat cover(size, CV_32F, cv::Scalar(0)), unused(size, CV_32F, cv::Scalar(0));
  const double reach = 1.1 * std::max(s.a, s.b) + 6;
  const cv::Rect box =
      cv::Rect(int(s.cx - reach), int(s.cy - reach), int(2 * reach), int(2 * reach)) &
      cv::Rect(0, 0, size.width, size.height);
  rasterise(s, box, cover, unused);
  r.truth = cv::Mat::zeros(size, CV_8UC1);
  for (int y = box.y; y < box.y + box.height; ++y)
    for (int x = box.x; x < box.x + box.width; ++x)
      if (s.layer(x, y) > 0) r.truth.at<std::uint8_t>(y, x) = 255;
  // Tissue with texture, gel with a little noise, the gel within a few pixels of the body tinted
  // by the tissue seen through it (25 % at the edge, fading over 3 px); edge pixels mix by area.
  const cv::Vec3f gel(40, 70, 160), tissue(185, 120, 95);
  cv::Mat outside_dist;
  cv::distanceTransform(~r.truth, outside_dist, cv::DIST_L2, 5);
  cv::Mat texture(size, CV_32F);
  cv::randn(texture, 0, 1);
  cv::GaussianBlur(texture, texture, cv::Size(0, 0), 2.0);
  r.rgb.create(size, CV_8UC3);
  for (int y = 0; y < size.height; ++y) {
    for (int x = 0; x < size.width; ++x) {
      const float cov = cover.at<float>(y, x);
      const float t = 25.f * texture.at<float>(y, x);
      const cv::Vec3f tis(tissue[0] + t, tissue[1] + 0.6f * t, tissue[2] + 0.5f * t);
      const float alpha = 0.25f * std::exp(-(outside_dist.at<float>(y, x) - 0.5f) / 3.f);
      const cv::Vec3f g = (1.f - alpha) * gel + alpha * tis;
      const cv::Vec3f v = cov * tis + (1.f - cov) * g;
      cv::Vec3b& o = r.rgb.at<cv::Vec3b>(y, x);
      for (int k = 0; k < 3; ++k)
        o[k] = cv::saturate_cast<std::uint8_t>(v[k] + 3.f * n01(rng));
    }
  }
  return r;
}

double iou(const cv::Mat& a, const cv::Mat& b) {
  const double inter = cv::countNonZero(a & b), uni = cv::countNonZero(a | b);
  return uni > 0 ? inter / uni : 1.0;
}

// Mean outward offset of the mask's edge from the true edge (pixels): area difference over the
// true outline's length.
double edge_offset(const cv::Mat& mask, const cv::Mat& truth) {
  cv::Mat eroded;
  cv::erode(truth, eroded, cv::Mat());
  const double perimeter = cv::countNonZero(truth & ~eroded);
  return perimeter > 0 ? (cv::countNonZero(mask) - cv::countNonZero(truth)) / perimeter : 0.0;
}

struct Row {
  int area;
  double iou, offset;
};

// compute_mask on the slices of `head` whose cross-sections have `areas` pixels.
std::vector<Row> run_stack(const Head& head, const std::vector<double>& areas, const CtModel& model,
                           const vp::MaskOptions& options, double* stack_iou, const char* title) {
  const cv::Size size(1024, 608);
  std::vector<Row> rows;
  double inter = 0, uni = 0;
  std::printf("%s\n| true area px | IoU | edge offset px |\n|---|---|---|\n", title);
  std::uint32_t seed = 100;
  for (double area : areas) {
    const Rendered r = render(head, head.z_for_area(area), size, model, seed++);
    const cv::Mat m = vp::compute_mask(r.rgb, &r.ct, r.out_to_ct, options, 0.33 * 0.33).mask;
    rows.push_back({cv::countNonZero(r.truth), iou(m, r.truth), edge_offset(m, r.truth)});
    std::printf("| %d | %.4f | %+.3f |\n", rows.back().area, rows.back().iou, rows.back().offset);
    inter += cv::countNonZero(m & r.truth);
    uni += cv::countNonZero(m | r.truth);
  }
  *stack_iou = inter / uni;
  std::printf("stack IoU %.4f\n", *stack_iou);
  return rows;
}

}  // namespace

// The top of a head: cross-sections from 200 000 px (a third of the frame) to 500 px, the CT
// slab 3 colour pixels thick (its edge smeared where the outline tapers), blurred, rotated and
// shifted against the colour grid. Default options (gel refinement on).
TEST(MaskEdge, TaperingHeadCap) {
  CtModel model;
  model.rotation = 0.05, model.shift = {0.3, -0.2};
  double stack = 0;
  const auto rows =
      run_stack(Head{}, {200000, 90000, 40000, 17760, 9396, 5000, 3000, 2000, 1008, 500}, model,
                vp::MaskOptions{}, &stack, "tapering head cap, refined");
  EXPECT_GE(stack, 0.995);
  for (const Row& r : rows) {
    // 1 % of the 1024×608 frame is 6 226 px.
    const double want = r.area >= 6226 ? 0.99 : r.area >= 1000 ? 0.975 : 0.95;
    EXPECT_GE(r.iou, want) << r.area << " px";
    EXPECT_LT(std::abs(r.offset), 0.25) << r.area << " px";
  }
}

// The CT alone (no gel refinement) where it can place the edge: a slice through the widest part
// (no smear along z), the skin and fat edge blurred by the PSF, off the CT grid.
TEST(MaskEdge, CtEdgeIsSubPixel) {
  CtModel model;
  model.rotation = -0.12, model.shift = {0.45, 0.7};
  model.slab_px = 0;
  vp::MaskOptions options;
  options.refine_gel = false;
  double stack = 0;
  for (double scale : {1.0, 0.45, 0.2, 0.07}) {
    Head head;
    head.a0 *= scale, head.b0 *= scale;
    const auto rows = run_stack(head, {vispack::kPi * head.a0 * head.b0}, model, options, &stack,
                                "widest section, CT only");
    // An edge 0.15 px off all round costs 2·0.15/r of the IoU (r: the mean radius).
    EXPECT_GE(rows[0].iou, 1.0 - 2.0 * 0.15 / std::sqrt(rows[0].area / vispack::kPi))
        << rows[0].area;
    EXPECT_LT(std::abs(rows[0].offset), 0.12) << rows[0].area;
  }
}

// A CT body 3 px larger than the colour body (a CT from a fatter day, or a holder bridge): the
// gel refinement must bring the edge back through the translucent tinted gel.
TEST(MaskEdge, GelRefinementFindsTheColourEdge) {
  CtModel model;
  model.grow_px = 3;
  model.slab_px = 0;
  double stack = 0;
  const auto rows = run_stack(Head{}, {200000, 17760, 3000}, model, vp::MaskOptions{}, &stack,
                              "CT 3 px too large, refined");
  for (const Row& r : rows) {
    EXPECT_LT(std::abs(r.offset), 0.25) << r.area << " px";
  }
}

// Without CT (a colour-only mask: no CT configured, a slice beyond the CT, a body's tip between
// CT slices) the colour threshold keeps edge pixels barely covered by tissue and the translucent
// gel tinted by the tissue next to it; the mask's edge must lie at the half-covered level all the
// same (it was 1 px outside: 11–15 % too much body on small sections).
TEST(MaskEdge, ColourOnlyEdgeLiesAtTheHalfCoveredLevel) {
  CtModel model;
  model.slab_px = 0;
  const Head head;
  const cv::Size size(1024, 608);
  std::uint32_t seed = 300;
  for (double area : {90000.0, 9396.0, 3000.0, 1008.0}) {
    const Rendered r = render(head, head.z_for_area(area), size, model, seed++);
    const cv::Mat m =
        vp::compute_mask(r.rgb, nullptr, r.out_to_ct, vp::MaskOptions{}, 0.33 * 0.33).mask;
    const double offset = edge_offset(m, r.truth), overlap = iou(m, r.truth);
    std::printf("colour only, %d px: IoU %.4f, edge offset %+.3f px\n", cv::countNonZero(r.truth),
                overlap, offset);
    EXPECT_LT(std::abs(offset), 0.3) << area << " px";
    EXPECT_GE(overlap, area >= 6226 ? 0.99 : 0.97) << area << " px";
  }
}

// A colour slice a third of the way between two CT slices 3 colour slices apart (the VH female:
// colour every 1/3 mm, CT every 1 mm) near the top of a head, where the outline moves by several
// pixels from one CT slice to the next (the cross-section shrinks to a fifth over the 6 colour
// pixels between them). The HU blend keeps the nearer slice's outline until half way (too small
// here); the outlines interpolated by shape (shape_blend_hu, the mask without refinement) come
// closer, and their union trimmed by the colour (the default, gel refinement on) finds the edge.
TEST(MaskEdge, BetweenTwoCtSlicesTheOutlineFollowsTheBody) {
  CtModel model;
  model.rotation = 0.05, model.shift = {0.3, -0.2};
  model.slab_px = 0;
  const Head head;
  const cv::Size size(1024, 608);
  const double level = vp::mask_edge_level_hu(vp::MaskOptions{}.hu_threshold);
  vp::MaskOptions ct_only;
  ct_only.refine_gel = false;
  std::uint32_t seed = 400;
  for (double area : {40000.0, 17760.0, 9396.0}) {
    const double z = head.z_for_area(area), dz = 2.0;  // colour pixels between colour slices
    const Rendered below = render(head, z - dz, size, model, seed++);
    const Rendered here = render(head, z, size, model, seed++);
    const Rendered above = render(head, z + 2 * dz, size, model, seed++);
    cv::Mat linear;
    cv::addWeighted(below.ct, 2.0 / 3.0, above.ct, 1.0 / 3.0, 0.0, linear);
    const cv::Mat shape = vp::shape_blend_hu(below.ct, above.ct, 1.0 / 3.0, level);
    const cv::Mat envelope = cv::max(below.ct, above.ct);
    auto mask_iou = [&](const cv::Mat& ct, const vp::MaskOptions& o) {
      return iou(vp::compute_mask(here.rgb, &ct, here.out_to_ct, o, 0.33 * 0.33).mask, here.truth);
    };
    const double lin = mask_iou(linear, ct_only), shp = mask_iou(shape, ct_only),
                 env = mask_iou(envelope, vp::MaskOptions{});
    std::printf(
        "between CT slices, %d px: IoU linear in HU %.4f, by shape %.4f, union trimmed "
        "by the colour %.4f\n",
        cv::countNonZero(here.truth), lin, shp, env);
    // By shape follows a steady outline (the widest of the three) and gains 0.04–0.12 over the
    // HU blend where the cap's outline moves fastest (it moves ∝ 1/√ there, not linearly).
    EXPECT_GE(shp, lin + 0.04) << area << " px";
    if (area >= 40000) {
      EXPECT_GE(shp, 0.985);
    }
    EXPECT_GE(env, 0.99) << area << " px";
  }
}

// The CT anchor: colour slice k aligned to CT slice k. See register/ct_anchor.h.
#include "vispack/pipeline/register/ct_anchor.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <utility>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/pipeline/imaging/outline.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/ecc.h"
#include "vispack/pipeline/register/rotation_search.h"

namespace vispack::pipeline {
namespace {

constexpr int kCaptureEdge = 128;                    // longer edge of the capture level, pixels
constexpr float kHuLow = -1000.f, kHuHigh = 1000.f;  // template clamp
// Nominal anchor error at confidence 1, working pixels, for a body of radius of gyration
// kSigmaRadiusWorkingPx or less; a larger body's outline averages more independent edge samples
// (their count grows with the perimeter), so its error falls as √(kSigmaRadiusWorkingPx / r).
// Measured against the phantoms' truth (anchor rotation error, RMS): 0.2° at r ≈ 20 working px
// (`anatomy`), 0.06° at r ≈ 60 (head-CT case), 0.008° at r ≈ 125 (`anatomy-vhp`), against
// 0.16°, 0.05° and 0.011° this model gives (with the measured lever). The solve inflates σ
// from the residuals where a stack's anchors are worse.
constexpr double kSigmaWorkingPx = 0.05;
constexpr double kSigmaRadiusWorkingPx = 10.0;
// The multimodal and outline ECCs also stop after an update that moves no pixel by more than
// this (working-grid pixels; EccOptions::min_step_px): a tenth of the anchor's own σ.
constexpr double kStepWorkingPx = 0.1 * kSigmaWorkingPx;
// The outline step (4) may move the translation this far (working pixels) and turn this far: on
// a body a few working pixels across (the `tiny` preset) the outline alone turned 1–2° away from
// a good multimodal estimate.
constexpr double kOutlineReachPx = 3.0;
constexpr double kOutlineTurnDeg = 1.0;
constexpr int kFeatures = 10;  // 1, r, g, b, r², g², b², rg, rb, gb

// Maps working-grid pixels to full-resolution pixels (pixel centres): x = (x_w + 0.5)/s − 0.5.
cv::Matx23d work_to_full(double sx, double sy) {
  return {1.0 / sx, 0, 0.5 / sx - 0.5, 0, 1.0 / sy, 0.5 / sy - 0.5};
}
cv::Matx23d full_to_work(double sx, double sy) {
  return {sx, 0, 0.5 * sx - 0.5, 0, sy, 0.5 * sy - 0.5};
}

// A full-resolution q → p matrix expressed on grids scaled by (sx, sy).
cv::Matx23d to_working(const cv::Matx23d& m, double sx, double sy) {
  return compose_affine(full_to_work(sx, sy), compose_affine(m, work_to_full(sx, sy)));
}
cv::Matx23d to_full(const cv::Matx23d& m, double sx, double sy) {
  return compose_affine(work_to_full(sx, sy), compose_affine(m, full_to_work(sx, sy)));
}

// ECC on (template, input) from `m` (template → input pixels); updates m. Returns rho or −1.
// `rejected` (optional): the caller's test of a result it would throw away; the iteration stops
// as a failure at the first iterate that fails it (EccOptions::diverged), instead of creeping on.
// `min_step_px` (this level's pixels): EccOptions::min_step_px.
double ecc(const cv::Mat& tmpl, const cv::Mat& input, cv::Matx23d& m, int iterations, double eps,
           int blur, std::function<bool(const cv::Matx23d&)> rejected = {},
           double min_step_px = 0.0) {
  EccOptions options;
  options.iterations = iterations;
  options.eps = eps;
  options.min_step_px = min_step_px;
  options.blur_size = blur;
  options.diverged = std::move(rejected);
  cv::Matx23d w = m;
  const std::optional<double> rho = ecc_euclidean(tmpl, input, w, options);
  if (!rho) return -1.0;
  m = w;
  return *rho;
}

// Median RGB of a 2-pixel frame along the border (the gel around the body).
cv::Vec3f border_colour(const cv::Mat& rgb) {
  std::array<std::vector<float>, 3> v;
  auto take = [&](int x, int y) {
    const cv::Vec3f& c = rgb.at<cv::Vec3f>(y, x);
    for (int i = 0; i < 3; ++i)
      v[std::size_t(i)].push_back(c[i]);
  };
  for (int x = 0; x < rgb.cols; ++x)
    for (int y : {0, 1, rgb.rows - 2, rgb.rows - 1})
      take(x, y);
  for (int y = 2; y < rgb.rows - 2; ++y)
    for (int x : {0, 1, rgb.cols - 2, rgb.cols - 1})
      take(x, y);
  cv::Vec3f out;
  for (int i = 0; i < 3; ++i) {
    auto& c = v[std::size_t(i)];
    std::nth_element(c.begin(), c.begin() + c.size() / 2, c.end());
    out[i] = c[c.size() / 2];
  }
  return out;
}

// Soft tissue map of the colour level: 0 at the gel colour, 1 beyond 80/255 from it.
cv::Mat colour_softbody(const cv::Mat& rgb) {
  const cv::Vec3f gel = border_colour(rgb);
  cv::Mat out(rgb.size(), CV_32F);
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3f* row = rgb.ptr<cv::Vec3f>(y);
    float* o = out.ptr<float>(y);
    for (int x = 0; x < rgb.cols; ++x) {
      const cv::Vec3f d = row[x] - gel;
      const float dist = std::sqrt(d.dot(d)) * 255.f;
      o[x] = std::clamp((dist - 20.f) / 60.f, 0.f, 1.f);
    }
  }
  return out;
}

// Polynomial features of one RGB value.
inline void features(const cv::Vec3f& c, double f[kFeatures]) {
  const double r = c[0], g = c[1], b = c[2];
  f[0] = 1, f[1] = r, f[2] = g, f[3] = b, f[4] = r * r, f[5] = g * g, f[6] = b * b;
  f[7] = r * g, f[8] = r * b, f[9] = g * b;
}

// Least-squares polynomial colour → template over the pixels where `valid` (warped colour
// `warped` on the template grid). Returns false when too few samples.
bool fit_colour_to_ct(const cv::Mat& warped, const cv::Mat& valid, const cv::Mat& tmpl,
                      double coef[kFeatures]) {
  cv::Matx<double, kFeatures, kFeatures> ata = cv::Matx<double, kFeatures, kFeatures>::zeros();
  cv::Matx<double, kFeatures, 1> atb = cv::Matx<double, kFeatures, 1>::zeros();
  int count = 0;
  double f[kFeatures];
  for (int y = 0; y < tmpl.rows; y += 2) {
    const cv::Vec3f* c = warped.ptr<cv::Vec3f>(y);
    const float* t = tmpl.ptr<float>(y);
    const std::uint8_t* v = valid.ptr<std::uint8_t>(y);
    for (int x = 0; x < tmpl.cols; x += 2) {
      if (!v[x]) continue;
      features(c[x], f);
      for (int i = 0; i < kFeatures; ++i) {
        for (int j = 0; j <= i; ++j)
          ata(i, j) += f[i] * f[j];
        atb(i) += f[i] * t[x];
      }
      ++count;
    }
  }
  if (count < 4 * kFeatures) return false;
  for (int i = 0; i < kFeatures; ++i) {
    for (int j = i + 1; j < kFeatures; ++j)
      ata(i, j) = ata(j, i);
    ata(i, i) += 1e-6 * count;  // a whisper of ridge: keeps grey slices (r = g = b) solvable
  }
  cv::Matx<double, kFeatures, 1> x;
  if (!cv::solve(ata, atb, x, cv::DECOMP_CHOLESKY) && !cv::solve(ata, atb, x, cv::DECOMP_SVD))
    return false;
  for (int i = 0; i < kFeatures; ++i)
    coef[i] = x(i);
  return true;
}

cv::Mat predict_ct(const cv::Mat& rgb, const double coef[kFeatures]) {
  cv::Mat out(rgb.size(), CV_32F);
  double f[kFeatures];
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3f* c = rgb.ptr<cv::Vec3f>(y);
    float* o = out.ptr<float>(y);
    for (int x = 0; x < rgb.cols; ++x) {
      features(c[x], f);
      double s = 0;
      for (int i = 0; i < kFeatures; ++i)
        s += coef[i] * f[i];
      o[x] = float(std::clamp(s, double(kHuLow), double(kHuHigh)));
    }
  }
  return out;
}

// A soft body map (0 outside, 1 inside, a ramp across the edge) reduced to the body: every
// part of its half level that the part rule keeps (outline.h; `rgb`, when given, the colour
// slice for its colour test, CV_32FC3 in 0..1), grown by two pixels for the soft edge. Fiducial
// tubes, holders and debris, which the other modality does not show, are cut off; arms, legs
// and toes all stay (the header: why the anchor must see them all).
cv::Mat body_only(cv::Mat soft, double min_part_px, const cv::Mat& rgb = cv::Mat(),
                  int* parts = nullptr) {
  PartRule rule;
  rule.min_area_px = min_part_px;
  cv::Mat rgb8;
  if (!rgb.empty()) rgb.convertTo(rgb8, CV_8UC3, 255.0);
  cv::Mat keep;
  // Holes filled first: the part rule judges a part's shape by its outline (lungs and cavities
  // would make a torso look like a band).
  PartCounts counts;
  cv::dilate(body_parts(fill_holes(soft > 0.5f), rule, &counts, rgb8), keep,
             cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)));
  soft.setTo(cv::Scalar(0.0), keep == 0);
  if (parts) *parts = counts.kept;
  return soft;
}

// The shift s that maximises the overlap Σ_p tmpl(p) · moving(p + s) of two soft body maps
// (the convention of cv::phaseCorrelate: moving ≈ tmpl shifted by s), by one zero-padded
// correlation through the DFT, refined by a parabola in x and in y. Every part counts with its
// area: the shift that overlaps both legs beats the one that lays one leg on the other.
cv::Point2d overlap_shift(const cv::Mat& tmpl, const cv::Mat& moving) {
  const int w = cv::getOptimalDFTSize(2 * tmpl.cols), h = cv::getOptimalDFTSize(2 * tmpl.rows);
  cv::Mat a = cv::Mat::zeros(h, w, CV_32F), b = cv::Mat::zeros(h, w, CV_32F);
  tmpl.copyTo(a(cv::Rect(0, 0, tmpl.cols, tmpl.rows)));
  moving.copyTo(b(cv::Rect(0, 0, moving.cols, moving.rows)));
  cv::Mat fa, fb, product, corr;
  cv::dft(a, fa, 0, tmpl.rows);
  cv::dft(b, fb, 0, moving.rows);
  cv::mulSpectrums(fb, fa, product, 0, true);  // F(moving) · conj(F(tmpl))
  cv::idft(product, corr, cv::DFT_REAL_OUTPUT | cv::DFT_SCALE);
  cv::Point peak;
  cv::minMaxLoc(corr, nullptr, nullptr, nullptr, &peak);
  auto at = [&](int x, int y) { return double(corr.at<float>((y + h) % h, (x + w) % w)); };
  auto vertex = [](double l, double c, double r) {
    const double d = l - 2.0 * c + r;
    return d < 0.0 ? std::clamp(0.5 * (l - r) / d, -0.5, 0.5) : 0.0;
  };
  const double c = at(peak.x, peak.y);
  const double dx = vertex(at(peak.x - 1, peak.y), c, at(peak.x + 1, peak.y));
  const double dy = vertex(at(peak.x, peak.y - 1), c, at(peak.x, peak.y + 1));
  // Indices past the middle are negative shifts.
  const double sx = (peak.x > w / 2 ? peak.x - w : peak.x) + dx;
  const double sy = (peak.y > h / 2 ? peak.y - h : peak.y) + dy;
  return {sx, sy};
}

// Capture on soft body masks (step 2 of the header): the template → input matrix at this level.
// At each angle two candidate shifts, phase correlation (sharp, led by the edges) and the
// overlap of the whole maps (overlap_shift: no window, every part by its area), ranked by the
// normalised correlation of the whole aligned maps.
std::optional<cv::Matx23d> capture(const cv::Mat& tmpl, const cv::Mat& input) {
  cv::Mat window;
  cv::createHanningWindow(window, tmpl.size(), CV_32F);
  const cv::Point2d cc = image_centre(tmpl.size());
  const cv::Mat tmpl_w = tmpl.mul(window);
  struct Candidate {
    double angle = 0, score = -2;
    cv::Matx23d m;
  };
  auto candidate = [&](double angle, cv::Point2d s) {
    Candidate cand;
    cand.angle = angle;
    const double a = angle * kPi / 180.0;
    const cv::Point2d rs(std::cos(a) * s.x - std::sin(a) * s.y,
                         std::sin(a) * s.x + std::cos(a) * s.y);
    cand.m = rigid_matrix({angle, rs.x, rs.y}, cc);
    cv::Mat aligned;
    cv::warpAffine(input, aligned, cv::Mat(cand.m), tmpl.size(),
                   cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
    cv::Mat score;
    cv::matchTemplate(aligned, tmpl, score, cv::TM_CCOEFF_NORMED);
    const float v = score.at<float>(0, 0);
    cand.score = std::isfinite(v) ? v : -1.0;
    return cand;
  };
  auto evaluate = [&](double angle) {
    const cv::Mat rotated = rotate_about_centre(input, angle);
    const Candidate phase = candidate(angle, cv::phaseCorrelate(tmpl_w, rotated.mul(window)));
    const Candidate overlap = candidate(angle, overlap_shift(tmpl, rotated));
    return overlap.score > phase.score ? overlap : phase;
  };
  // −10°..10°, refined by half steps and a parabola (register/rotation_search.h).
  const Candidate best = sweep_rotation(evaluate);
  if (best.score < 0.2) return std::nullopt;
  cv::Matx23d m = best.m;
  cv::Mat t, in;
  cv::GaussianBlur(tmpl, t, cv::Size(0, 0), 1.5);
  cv::GaussianBlur(input, in, cv::Size(0, 0), 1.5);
  cv::Matx23d refined = m;
  const double reach = 0.15 * std::max(tmpl.cols, tmpl.rows);
  auto moved = [&](const cv::Matx23d& w) {
    return std::hypot(w(0, 2) - m(0, 2), w(1, 2) - m(1, 2));
  };
  if (ecc(t, in, refined, 40, 1e-4, 1,
          [&](const cv::Matx23d& w) { return !(moved(w) < kEccRunawayFactor * reach); }) > 0.0 &&
      moved(refined) < reach)
    m = refined;
  return m;
}

cv::Mat downsample(const cv::Mat& image, double scale) {
  if (scale >= 0.999) return image;
  cv::Mat out;
  cv::resize(image, out,
             cv::Size(std::max(8, int(std::lround(image.cols * scale))),
                      std::max(8, int(std::lround(image.rows * scale)))),
             0, 0, cv::INTER_AREA);
  return out;
}

// Step 1 of the header: the CT slice as float, reduced to the body. Only the body takes part:
// what the CT shows around it (head-holder, table) has no counterpart in the colour slice and,
// beside a small body at the stack's ends, biases the alignment (rotation most). Everything
// outside the body (grown by one pixel, its partial-volume edge) becomes air; in that edge, what
// is denser than the threshold is not the body's partial volume but a holder or table touching
// it (an arm resting on the table): clamped to the threshold.
cv::Mat ct_body_only(const cv::Mat& ct_hu, const AnchorOptions& options) {
  cv::Mat ct32;
  ct_hu.convertTo(ct32, CV_32F);
  cv::Mat keep;
  const cv::Mat body = ct_body_mask(ct32, options.hu_threshold, options.min_part_ct_px);
  cv::dilate(body, keep, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(3, 3)));
  ct32.setTo(cv::Scalar(kHuLow), keep == 0);
  const cv::Mat edge = keep & ~body;
  cv::Mat clamped = cv::min(ct32, options.hu_threshold);
  clamped.copyTo(ct32, edge);
  return ct32;
}

// The body's size on the template (moments `mo` of its body pixels): its radius of gyration and
// the rotation's lever in colour pixels, and σ scaled by the radius (kSigmaRadiusWorkingPx).
void measure_body(const cv::Mat& tmpl, const cv::Moments& mo, double sx, double sy,
                  AnchorEstimate& est) {
  const double mx = mo.m10 / mo.m00, my = mo.m01 / mo.m00;
  const double var_x = mo.m20 / mo.m00 - mx * mx, var_y = mo.m02 / mo.m00 - my * my;
  // Radius of gyration in colour pixels (anisotropy of sx, sy is negligible).
  est.radius_px = std::sqrt(std::max(0.0, var_x / (sx * sx) + var_y / (sy * sy)));
  // The rotation's lever from the template's gradients about the centroid.
  cv::Mat smooth, gx, gy;
  cv::GaussianBlur(tmpl, smooth, cv::Size(0, 0), 1.0);
  cv::Sobel(smooth, gx, CV_32F, 1, 0, 3);
  cv::Sobel(smooth, gy, CV_32F, 0, 1, 3);
  double it = 0, ir = 0;
  for (int y = 0; y < gx.rows; ++y) {
    const float* px = gx.ptr<float>(y);
    const float* py = gy.ptr<float>(y);
    for (int x = 0; x < gx.cols; ++x) {
      const double tq = (x - mx) * py[x] - (y - my) * px[x];
      it += 0.5 * (double(px[x]) * px[x] + double(py[x]) * py[x]);
      ir += tq * tq;
    }
  }
  est.lever_px = it > 0 ? std::sqrt(ir / it) / sx : 0.0;
  const double radius_working = est.radius_px * sx;
  est.sigma_px *=
      std::sqrt(kSigmaRadiusWorkingPx / std::max(kSigmaRadiusWorkingPx, radius_working));
}

// Step 3 of the header: multimodal ECC of the colour (through a fitted colour → HU polynomial)
// against the template, from `start` (working grid → input). Two passes: half working
// resolution, then full; the polynomial refitted before each. Returns the refined matrix and
// its correlation in *rho_out, or nothing when a fit fails or the refinement diverges.
std::optional<cv::Matx23d> refine_multimodal(const cv::Mat& tmpl, const cv::Mat& colour,
                                             cv::Matx23d start, int iterations, double* rho_out) {
  double rho = -1.0;
  for (double level : {0.5, 1.0}) {
    const cv::Mat t = downsample(tmpl, level), col = downsample(colour, level);
    const double lx = double(t.cols) / tmpl.cols, ly = double(t.rows) / tmpl.rows;
    cv::Matx23d ml = to_working(start, lx, ly);  // working grid → this level
    cv::Mat warped, valid;
    cv::warpAffine(col, warped, cv::Mat(ml), t.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                   cv::BORDER_CONSTANT, cv::Scalar::all(-1));
    cv::Mat ones(col.size(), CV_8U, cv::Scalar(255));
    cv::warpAffine(ones, valid, cv::Mat(ml), t.size(), cv::INTER_NEAREST | cv::WARP_INVERSE_MAP,
                   cv::BORDER_CONSTANT, cv::Scalar(0));
    double coef[kFeatures];
    if (!fit_colour_to_ct(warped, valid, t, coef)) return std::nullopt;
    const cv::Mat predicted = predict_ct(col, coef);
    const cv::Matx23d before = ml;
    // A refinement that runs far from its start has diverged.
    auto too_far = [&, reach = 0.1 * std::max(t.cols, t.rows)](const cv::Matx23d& w, double k) {
      return std::hypot(w(0, 2) - before(0, 2), w(1, 2) - before(1, 2)) > k * reach;
    };
    // A wide blur widens the basin at half resolution; the final pass blurs less, as the
    // polynomial is applied before the blur (edges mixing two tissues map imperfectly).
    rho = ecc(
        t, predicted, ml, iterations, 1e-5, level < 1.0 ? 5 : 3,
        [&](const cv::Matx23d& w) { return too_far(w, kEccRunawayFactor); }, kStepWorkingPx * lx);
    if (rho < 0.0 || too_far(ml, 1.0)) return std::nullopt;
    start = to_full(ml, lx, ly);
  }
  *rho_out = rho;
  return start;
}

// Step 4 of the header: outline refinement, ECC of the soft body masks at full working
// resolution from the multimodal result `m`. The body's outline is the one feature both
// modalities show the same way; the intensity map of step 3 is not exact inside the body
// (texture the CT does not resolve, tissues of one colour and two densities), which biases the
// rotation of a small body by tenths of a degree. Kept when it converges near its start
// (kOutlineReachPx, kOutlineTurnDeg); otherwise `m` is returned.
cv::Matx23d refine_outline(const cv::Mat& soft_ct, const cv::Mat& soft_colour, const cv::Matx23d& m,
                           int iterations) {
  cv::Matx23d outline = m;
  auto within = [&](const cv::Matx23d& w, double k) {
    return std::hypot(w(0, 2) - m(0, 2), w(1, 2) - m(1, 2)) < k * kOutlineReachPx &&
           std::abs(std::atan2(w(1, 0), w(0, 0)) - std::atan2(m(1, 0), m(0, 0))) <
               k * kOutlineTurnDeg * kPi / 180.0;
  };
  if (ecc(
          soft_ct, soft_colour, outline, 2 * iterations, 1e-7, 3,
          [&](const cv::Matx23d& w) { return !within(w, kEccRunawayFactor); },
          kStepWorkingPx) > 0.0 &&
      within(outline, 1.0))
    return outline;
  return m;
}

}  // namespace

double anchor_working_scale(const Config& config) {
  if (!config.ct) return 0.0;
  return std::min(1.0, config.spacing_mm[0] / config.ct->pixel_spacing_mm[0]);
}

nlohmann::json to_json(const AnchorEstimate& a) {
  return {{"ok", a.ok},
          {"rotation_deg", a.transform.rotation_deg},
          {"dx_px", a.transform.dx_px},
          {"dy_px", a.transform.dy_px},
          {"confidence", a.confidence},
          {"correlation", a.correlation},
          {"body_fraction", a.body_fraction},
          {"radius_px", a.radius_px},
          {"lever_px", a.lever_px},
          {"sigma_px", a.sigma_px},
          {"parts_ct", a.parts_ct},
          {"parts_colour", a.parts_colour}};
}

AnchorEstimate anchor_from_json(const nlohmann::json& j, const std::string& what) {
  try {
    AnchorEstimate a;
    a.ok = j.at("ok").get<bool>();
    a.transform = {j.at("rotation_deg").get<double>(), j.at("dx_px").get<double>(),
                   j.at("dy_px").get<double>()};
    a.confidence = j.at("confidence").get<double>();
    a.correlation = j.at("correlation").get<double>();
    a.body_fraction = j.at("body_fraction").get<double>();
    a.radius_px = j.at("radius_px").get<double>();
    a.lever_px = j.value("lever_px", a.radius_px);
    a.sigma_px = j.at("sigma_px").get<double>();
    a.parts_ct = j.value("parts_ct", 0);  // older records (before the part counts) have none
    a.parts_colour = j.value("parts_colour", 0);
    if (!(a.confidence >= 0.0 && a.confidence <= 1.0) || !(a.sigma_px >= 0.0) ||
        !std::isfinite(a.transform.dx_px) || !std::isfinite(a.transform.dy_px) ||
        !std::isfinite(a.transform.rotation_deg))
      throw FormatError("value out of range");
    return a;
  } catch (const std::exception& e) {
    throw FormatError(cat(what, ": malformed anchor record: ", e.what()));
  }
}

AnchorEstimate estimate_ct_anchor(const RegisterFrame& frame, const cv::Mat& ct_hu,
                                  const Similarity& ct_to_rgb, const AnchorOptions& options,
                                  const Rigid* initial) {
  if (frame.anchor_colour.empty() || frame.anchor_scale <= 0.0)
    throw Error("estimate_ct_anchor: the frame has no anchor level (prepare_frame anchor_scale)");
  if (ct_hu.empty() || ct_hu.channels() != 1) throw Error("estimate_ct_anchor: empty CT slice");
  AnchorEstimate est;
  const cv::Mat& colour = frame.anchor_colour;
  const cv::Size full = frame.full_size;
  const double sx = double(colour.cols) / full.width, sy = double(colour.rows) / full.height;
  const cv::Point2d c_full = image_centre(full);
  est.sigma_px = kSigmaWorkingPx / sx;
  // 1. Template: the CT on the working output grid.
  const cv::Mat ct32 = ct_body_only(ct_hu, options);
  const cv::Matx23d out_to_ct =
      invert_affine(similarity_matrix(ct_to_rgb, image_centre(ct32.size()), c_full));
  cv::Mat ct_work;
  cv::warpAffine(ct32, ct_work, cv::Mat(compose_affine(out_to_ct, work_to_full(sx, sy))),
                 colour.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT,
                 cv::Scalar(kHuLow));
  cv::Mat tmpl = cv::max(cv::min(ct_work, kHuHigh), kHuLow);
  const cv::Mat body = ct_work > options.hu_threshold;
  const cv::Moments mo = cv::moments(body, true);
  est.body_fraction = mo.m00 / double(body.total());
  if (est.body_fraction < 1e-3) return est;  // nothing to anchor on
  measure_body(tmpl, mo, sx, sy, est);
  // Working-grid template → input matrix.
  cv::Matx23d m;
  bool have = false;
  // The part rule's minimum area on the working grid (CT pixels → colour pixels → working).
  const double min_part_work = options.min_part_ct_px * ct_to_rgb.scale * ct_to_rgb.scale * sx * sy;
  const double capture_scale =
      std::min(1.0, double(kCaptureEdge) / std::max(colour.cols, colour.rows));
  const cv::Mat soft_ct = [&] {
    cv::Mat s;
    ct_work.convertTo(s, CV_32F, 1.0 / 600.0, -(options.hu_threshold - 300.0) / 600.0);
    return body_only(cv::Mat(cv::max(cv::min(s, 1.0), 0.0)), min_part_work, cv::Mat(),
                     &est.parts_ct);
  }();
  const cv::Mat soft_colour =
      body_only(colour_softbody(colour), min_part_work, colour, &est.parts_colour);
  double rho = -1.0;
  if (initial) {
    m = to_working(rigid_matrix(*initial, c_full), sx, sy);
    if (auto r = refine_multimodal(tmpl, colour, m, options.iterations, &rho); r && rho > 0.5)
      m = *r, have = true;
  }
  if (!have) {
    const cv::Mat st = downsample(soft_ct, capture_scale),
                  sc = downsample(soft_colour, capture_scale);
    const double lx = double(st.cols) / tmpl.cols, ly = double(st.rows) / tmpl.rows;
    const std::optional<cv::Matx23d> cap = capture(st, sc);
    if (!cap) return est;
    if (auto r = refine_multimodal(tmpl, colour, to_full(*cap, lx, ly), options.iterations, &rho)) {
      m = *r;
      have = true;
    }
  }
  if (!have) return est;
  m = refine_outline(soft_ct, soft_colour, m, options.iterations);
  est.transform = rigid_from_matrix(to_full(m, sx, sy), c_full);
  est.correlation = std::clamp(rho, 0.0, 1.0);
  est.confidence =
      std::clamp((rho - 0.4) / 0.4, 0.0, 1.0) * std::clamp(est.body_fraction / 0.03, 0.0, 1.0);
  est.ok = est.confidence > 0.0;
  return est;
}

}  // namespace vispack::pipeline

// Pairwise registration (phase correlation + ECC) and the least-squares chaining of the pair
// graph. See register.h for the method.
#include "vispack/pipeline/register.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <mutex>
#include <queue>

#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"

namespace vispack::pipeline {
namespace {

constexpr int kCoarseEdge = 256;      // longer edge of the coarse level, pixels
constexpr double kAngleRange = 10.0;  // coarse rotation search: −10°..10°
constexpr double kAngleStep = 2.5;
constexpr int kLookBack = 4;                 // edges reach back over at most 4 slices
constexpr int kFiducialColourDistance = 40;  // RGB distance from the gel of a fiducial blob
constexpr double kPi = 3.14159265358979323846;
// Fine ECC stops when the correlation improves by less than this per iteration: from the
// coarse estimate (within ~0.1 coarse px) it converges in a few iterations.
constexpr double kFineEps = 1e-5;

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

// Rotates `image` about its centre so that out(x) = image(c + R(φ)(x − c)).
cv::Mat rotate_about_centre(const cv::Mat& image, double angle_deg) {
  if (angle_deg == 0.0) return image;
  cv::Mat out;
  cv::warpAffine(image, out, cv::Mat(rigid_matrix({angle_deg, 0, 0}, image_centre(image.size()))),
                 image.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
  return out;
}

// ECC at one level; `m` (full-resolution j→k matrix) is updated in place. Returns rho or throws.
double ecc_level(const cv::Mat& from, const cv::Mat& to, double scale, cv::Matx23d& m,
                 int iterations, double eps) {
  cv::Matx23d ms = scale_affine(m, scale);
  cv::Mat warp(2, 3, CV_32F);
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      warp.at<float>(r, c) = float(ms(r, c));
  const double rho = cv::findTransformECC(
      from, to, warp, cv::MOTION_EUCLIDEAN,
      cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, iterations, eps),
      cv::noArray(), 1);  // the frames are pre-blurred (prepare_frame)
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      ms(r, c) = warp.at<float>(r, c);
  m = unscale_affine(ms, scale);
  return rho;
}

// Step 3 of estimate_pair: ECC at ecc_scale from `m` (full-resolution matrix of `start`).
// On success sets est.relative, est.quality (the correlation) and est.ecc_ok; a refinement that
// moves more than 4 coarse pixels from `start` has diverged and counts as a failure.
bool refine_fine(const RegisterFrame& from, const RegisterFrame& to, const RegisterOptions& options,
                 const Rigid& start, cv::Matx23d m, PairEstimate& est) {
  const cv::Point2d centre = image_centre(from.full_size);
  try {
    const double rho = ecc_level(from.fine, to.fine, from.fine_scale, m,
                                 std::max(1, options.ecc_iterations), kFineEps);
    const Rigid refined = rigid_from_matrix(m, centre);
    const Rigid diff{refined.rotation_deg - start.rotation_deg, refined.dx_px - start.dx_px,
                     refined.dy_px - start.dy_px};
    if (std::isfinite(rho) && rigid_motion_px(diff, from.full_size) < 4.0 / from.coarse_scale) {
      est.relative = refined;
      est.quality = std::clamp(rho, 0.0, 1.0);
      est.ecc_ok = true;
      return true;
    }
  } catch (const cv::Exception&) {
    // ECC did not converge.
  }
  return false;
}

// ---- banded symmetric positive-definite solver (normal equations of the pair graph) ----
class BandedSpd {
 public:
  BandedSpd(int n, int band) : n_(n), band_(band), a_(std::size_t(n) * (band + 1), 0.0) {}
  int size() const { return n_; }
  void add(int i, int j, double v) {  // symmetric entry (i, j) += v, |i − j| <= band
    if (i < j) std::swap(i, j);
    a_[std::size_t(i) * (band_ + 1) + (i - j)] += v;
  }
  // In-place Cholesky (L stored in the band).
  void factor() {
    for (int i = 0; i < n_; ++i) {
      for (int j = std::max(0, i - band_); j <= i; ++j) {
        double s = at(i, j);
        for (int k = std::max(0, i - band_); k < j; ++k)
          s -= at(i, k) * at(j, k);
        if (i == j) {
          at(i, i) = std::sqrt(std::max(s, 1e-300));
        } else {
          at(i, j) = s / at(j, j);
        }
      }
    }
  }
  // Forward/back substitution with the factor.
  std::vector<double> solve(std::vector<double> y) const {
    for (int i = 0; i < n_; ++i) {
      for (int k = std::max(0, i - band_); k < i; ++k)
        y[i] -= at(i, k) * y[k];
      y[i] /= at(i, i);
    }
    for (int i = n_ - 1; i >= 0; --i) {
      for (int k = i + 1; k <= std::min(n_ - 1, i + band_); ++k)
        y[i] -= at(k, i) * y[k];
      y[i] /= at(i, i);
    }
    return y;
  }

 private:
  double& at(int i, int j) { return a_[std::size_t(i) * (band_ + 1) + (i - j)]; }
  double at(int i, int j) const { return a_[std::size_t(i) * (band_ + 1) + (i - j)]; }
  int n_, band_;
  std::vector<double> a_;
};

// Normal equations [[B, C], [Cᵀ, D]] [x; y] = [b; e]: B banded over the first n unknowns (the
// slices), C and D dense for the m border unknowns (free frames). Solved by the Schur
// complement: S = D − Cᵀ B⁻¹ C (m × m), y = S⁻¹ (e − Cᵀ B⁻¹ b), x = B⁻¹ (b − C y).
class BorderedSystem {
 public:
  BorderedSystem(int n, int band, int m)
      : n_(n),
        m_(m),
        b_mat_(n, band),
        c_(std::size_t(n) * m, 0.0),
        d_(std::size_t(m) * m, 0.0),
        rhs_(std::size_t(n + m), 0.0) {}
  void add(int i, int j, double v) {  // symmetric entry (i, j) += v (i ≠ j: both triangles)
    if (i < n_ && j < n_) {
      b_mat_.add(i, j, v);
    } else if (i >= n_ && j >= n_) {
      d_[std::size_t(i - n_) * m_ + (j - n_)] += v;
      if (i != j) d_[std::size_t(j - n_) * m_ + (i - n_)] += v;
    } else {
      if (i >= n_) std::swap(i, j);
      c_[std::size_t(i) * m_ + (j - n_)] += v;
    }
  }
  void add_rhs(int i, double v) { rhs_[std::size_t(i)] += v; }
  std::vector<double> solve() {
    b_mat_.factor();
    std::vector<double> b(rhs_.begin(), rhs_.begin() + n_);
    std::vector<double> x = b_mat_.solve(b);
    if (m_ == 0) return x;
    // X = B⁻¹ C, column by column.
    std::vector<std::vector<double>> xc(static_cast<std::size_t>(m_));
    for (int c = 0; c < m_; ++c) {
      std::vector<double> col(static_cast<std::size_t>(n_));
      for (int i = 0; i < n_; ++i)
        col[std::size_t(i)] = c_[std::size_t(i) * m_ + c];
      xc[std::size_t(c)] = b_mat_.solve(col);
    }
    cv::Mat s(m_, m_, CV_64F), r(m_, 1, CV_64F);
    for (int a = 0; a < m_; ++a) {
      double ra = rhs_[std::size_t(n_ + a)];
      for (int i = 0; i < n_; ++i)
        ra -= c_[std::size_t(i) * m_ + a] * x[std::size_t(i)];
      r.at<double>(a) = ra;
      for (int c = 0; c < m_; ++c) {
        double v = d_[std::size_t(a) * m_ + c];
        for (int i = 0; i < n_; ++i)
          v -= c_[std::size_t(i) * m_ + a] * xc[std::size_t(c)][std::size_t(i)];
        s.at<double>(a, c) = v;
      }
    }
    cv::Mat y;
    cv::solve(s, r, y, cv::DECOMP_SVD);
    for (int i = 0; i < n_; ++i)
      for (int c = 0; c < m_; ++c)
        x[std::size_t(i)] -= xc[std::size_t(c)][std::size_t(i)] * y.at<double>(c);
    for (int c = 0; c < m_; ++c)
      x.push_back(y.at<double>(c));
    return x;
  }

 private:
  int n_, m_;
  BandedSpd b_mat_;
  std::vector<double> c_, d_, rhs_;
};

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

RegisterFrame prepare_frame(const cv::Mat& slice, const RegisterOptions& options) {
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
  // The 5×5 Gaussian that ECC applies to both images of every pair, done once per frame
  // (a frame takes part in up to four pairs).
  const bool shared = f.coarse.data == f.fine.data;
  cv::GaussianBlur(f.fine, f.fine, cv::Size(5, 5), 0, 0);
  if (shared) {
    f.coarse = f.fine;
  } else {
    cv::GaussianBlur(f.coarse, f.coarse, cv::Size(5, 5), 0, 0);
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

PairEstimate estimate_pair(const RegisterFrame& from, const RegisterFrame& to,
                           const RegisterOptions& options, const Rigid* initial) {
  if (from.full_size != to.full_size || from.fine.size() != to.fine.size())
    throw Error(cat("estimate_pair: slices differ in size (", from.full_size.width, "x",
                    from.full_size.height, " and ", to.full_size.width, "x", to.full_size.height,
                    ")"));
  PairEstimate est;
  if (options.method == "none") {
    est.quality = 1.0;
    est.ecc_ok = true;
    return est;
  }
  const cv::Point2d centre = image_centre(from.full_size);
  // A good starting estimate (a skip edge composed from two neighbour edges): the fine step
  // alone; the full search only if that fails.
  if (initial && options.method == "phase+ecc") {
    PairEstimate quick;
    if (refine_fine(from, to, options, *initial, rigid_matrix(*initial, centre), quick))
      return quick;
  }
  // 1. Coarse: phase correlation at a rotation φ of the `to` slice. The phase-correlation peak
  //    favours interpolated (smoother) images, so candidates are ranked by the normalised
  //    correlation of the aligned images instead.
  cv::Mat window;
  cv::createHanningWindow(window, from.coarse.size(), CV_32F);
  const cv::Point2d cc = image_centre(from.coarse.size());
  const cv::Rect inner(from.coarse.cols / 10, from.coarse.rows / 10, from.coarse.cols * 8 / 10,
                       from.coarse.rows * 8 / 10);
  const cv::Mat from_inner = from.coarse(inner);
  // cv::phaseCorrelate multiplies its inputs by the window in place (OpenCV 4.6), so the
  // window is applied here to copies and no window is passed.
  const cv::Mat from_windowed = from.coarse.mul(window);
  struct Candidate {
    double angle, response, score;
    cv::Point2d shift;  // coarse pixels, rotated frame: W(x) = c + R(φ)(x + s − c)
  };
  auto evaluate = [&](double angle) {
    Candidate cand{angle, 0.0, -2.0, {}};
    cv::Mat rotated = rotate_about_centre(to.coarse, angle);
    cand.shift =
        cv::phaseCorrelate(from_windowed, rotated.mul(window), cv::noArray(), &cand.response);
    const double a = angle * kPi / 180.0;
    const cv::Point2d rs(std::cos(a) * cand.shift.x - std::sin(a) * cand.shift.y,
                         std::sin(a) * cand.shift.x + std::cos(a) * cand.shift.y);
    cv::Mat aligned;
    cv::warpAffine(to.coarse, aligned, cv::Mat(rigid_matrix({angle, rs.x, rs.y}, cc)),
                   from.coarse.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                   cv::BORDER_REPLICATE);
    cv::Mat score;
    cv::matchTemplate(aligned(inner), from_inner, score, cv::TM_CCOEFF_NORMED);
    cand.score = std::isfinite(score.at<float>(0, 0)) ? score.at<float>(0, 0) : -1.0;
    return cand;
  };
  auto to_rigid = [&](const Candidate& c) {
    const double a = c.angle * kPi / 180.0;
    const cv::Point2d rs(std::cos(a) * c.shift.x - std::sin(a) * c.shift.y,
                         std::sin(a) * c.shift.x + std::cos(a) * c.shift.y);
    return rigid_from_matrix(
        unscale_affine(rigid_matrix({c.angle, rs.x, rs.y}, cc), from.coarse_scale), centre);
  };
  // The sweep over −10°..10°, refined by half steps and a parabola.
  auto sweep = [&]() {
    std::vector<Candidate> grid;
    for (double a = -kAngleRange; a <= kAngleRange + 1e-9; a += kAngleStep)
      grid.push_back(evaluate(a));
    std::size_t bi = 0;
    for (std::size_t i = 1; i < grid.size(); ++i)
      if (grid[i].score > grid[bi].score) bi = i;
    Candidate best = grid[bi];
    Candidate lo = evaluate(best.angle - kAngleStep * 0.5),
              hi = evaluate(best.angle + kAngleStep * 0.5);
    const double denom = lo.score - 2.0 * best.score + hi.score;
    double angle = best.angle;
    if (denom < 0.0) {
      angle += std::clamp(0.5 * (lo.score - hi.score) / denom, -0.5, 0.5) * kAngleStep * 0.5;
    } else if (lo.score > best.score || hi.score > best.score) {
      angle = lo.score > hi.score ? lo.angle : hi.angle;
    }
    if (angle != best.angle) {
      Candidate refined = evaluate(angle);
      if (refined.score >= std::max(best.score, std::max(lo.score, hi.score)) - 1e-3) {
        best = refined;
      } else {
        best = lo.score > hi.score ? (lo.score > best.score ? lo : best)
                                   : (hi.score > best.score ? hi : best);
      }
    }
    return best;
  };
  // Coarse ECC from a phase estimate; returns rho (−1 on failure) and updates `m`.
  auto coarse_ecc = [&](cv::Matx23d& m) {
    try {
      const double rho = ecc_level(from.coarse, to.coarse, from.coarse_scale, m, 30, 1e-4);
      return std::isfinite(rho) ? rho : -1.0;
    } catch (const cv::Exception&) {
      return -1.0;
    }
  };
  Candidate best{};
  if (options.method == "phase") {
    best = sweep();
  } else {
    best = evaluate(0.0);
  }
  est.response = std::clamp(best.response, 0.0, 1.0);
  est.relative = to_rigid(best);
  est.quality = std::clamp(best.score, 0.0, 1.0);
  if (options.method == "phase") return est;

  // 2. Coarse ECC from the 0° estimate; the sweep only when that is not confident.
  constexpr double kConfident = 0.85;
  Rigid start = est.relative;
  cv::Matx23d m = rigid_matrix(start, centre);
  double rho_coarse = coarse_ecc(m);
  if (rho_coarse < kConfident) {
    Candidate swept = sweep();
    cv::Matx23d m2 = rigid_matrix(to_rigid(swept), centre);
    const double rho2 = coarse_ecc(m2);
    if (rho2 > rho_coarse || (rho_coarse < 0 && swept.score > best.score)) {
      best = swept;
      start = to_rigid(swept);
      m = m2;
      rho_coarse = rho2;
      est.response = std::clamp(best.response, 0.0, 1.0);
      est.relative = start;
      est.quality = std::clamp(best.score, 0.0, 1.0);
    }
  }
  if (rho_coarse < 0) {
    m = rigid_matrix(start, centre);  // coarse ECC failed: from the phase estimate
  } else {
    start = rigid_from_matrix(m, centre);
    est.relative = start;
  }

  // 3. ECC at ecc_scale.
  if (!refine_fine(from, to, options, start, m, est)) est.quality = std::min(est.quality, 0.5);
  return est;
}

std::vector<Rigid> solve_chain(int n, const std::vector<PairEdge>& edges, int free_nodes) {
  const int m = std::max(free_nodes, 0);
  const int total = std::max(n, 0) + m;
  std::vector<Rigid> out(std::size_t(std::max(total, 0)));
  if (n <= 1 && m == 0) return out;
  int band = 1;
  std::vector<std::vector<int>> adjacency(static_cast<std::size_t>(total));
  for (const auto& e : edges) {
    if (e.from < 0 || e.to < 0 || e.from >= total || e.to >= total || e.from == e.to)
      throw Error(cat("solve_chain: edge ", e.from, "->", e.to, " outside the stack of ", n,
                      " slices and ", m, " free frames"));
    if (e.from < n && e.to < n) band = std::max(band, std::abs(e.to - e.from));
    adjacency[std::size_t(e.from)].push_back(e.to);
    adjacency[std::size_t(e.to)].push_back(e.from);
  }
  // Nodes connected to the reference.
  std::vector<bool> reached(std::size_t(total), false);
  std::queue<int> queue;
  reached[0] = true;
  queue.push(0);
  while (!queue.empty()) {
    int i = queue.front();
    queue.pop();
    for (int j : adjacency[std::size_t(i)])
      if (!reached[std::size_t(j)]) reached[std::size_t(j)] = true, queue.push(j);
  }
  // A tiny prior pins unreached nodes (and keeps the system positive definite).
  constexpr double kPrior = 1e-9;
  // Rotations: θ_to − θ_from = φ; θ_0 fixed by a strong prior.
  BorderedSystem rot(n, band, m);
  rot.add(0, 0, 1e9);
  for (int i = 1; i < total; ++i)
    rot.add(i, i, kPrior);
  for (const auto& e : edges) {
    const double w = e.weight;
    rot.add(e.to, e.to, w);
    rot.add(e.from, e.from, w);
    rot.add(e.to, e.from, -w);
    rot.add_rhs(e.to, w * e.relative.rotation_deg);
    rot.add_rhs(e.from, -w * e.relative.rotation_deg);
  }
  std::vector<double> theta = rot.solve();
  theta[0] = 0.0;
  // Shifts: d_to − R(θ_to − θ_from) d_from = e (unknowns interleaved x, y per node).
  BorderedSystem shift(2 * n, 2 * band + 1, 2 * m);
  shift.add(0, 0, 1e9);
  shift.add(1, 1, 1e9);
  for (int i = 2; i < 2 * total; ++i)
    shift.add(i, i, kPrior);
  for (const auto& e : edges) {
    const double a = (theta[std::size_t(e.to)] - theta[std::size_t(e.from)]) * kPi / 180.0;
    const double co = std::cos(a), si = std::sin(a);
    const double w = e.weight;
    // Row x: +1·x_to − co·x_from + si·y_from = ex;  row y: +1·y_to − si·x_from − co·y_from = ey.
    const double rows[2][3] = {{1.0, -co, si}, {1.0, -si, -co}};
    const double rhs[2] = {e.relative.dx_px, e.relative.dy_px};
    for (int r = 0; r < 2; ++r) {
      const int idx[3] = {2 * e.to + r, 2 * e.from, 2 * e.from + 1};
      for (int p = 0; p < 3; ++p) {
        for (int q = 0; q <= p; ++q) {
          const double v = w * rows[r][p] * rows[r][q];
          if (idx[p] == idx[q] && p != q) {
            shift.add(idx[p], idx[q], 2.0 * v);
          } else {
            shift.add(idx[p], idx[q], v);
          }
        }
        shift.add_rhs(idx[p], w * rows[r][p] * rhs[r]);
      }
    }
  }
  std::vector<double> d = shift.solve();
  for (int i = 1; i < total; ++i) {
    if (!reached[std::size_t(i)]) continue;
    out[std::size_t(i)] = {theta[std::size_t(i)], d[2 * std::size_t(i)], d[2 * std::size_t(i) + 1]};
  }
  return out;
}

nlohmann::json to_json(const SlicePairs& p) {
  nlohmann::json edges = nlohmann::json::array();
  for (const auto& e : p.edges)
    edges.push_back({{"from", e.from},
                     {"to", e.to},
                     {"rotation_deg", e.relative.rotation_deg},
                     {"dx_px", e.relative.dx_px},
                     {"dy_px", e.relative.dy_px},
                     {"weight", e.weight}});
  nlohmann::json fiducials = nlohmann::json::array();
  for (const auto& f : p.fiducials)
    fiducials.push_back({f.x, f.y});
  return {{"index", p.index},
          {"black", p.black},
          {"duplicate_of", p.duplicate_of ? nlohmann::json(*p.duplicate_of) : nlohmann::json()},
          {"pixel_hash", hex64(p.pixel_hash)},
          {"quality", p.quality},
          {"edges", edges},
          {"fiducials", fiducials}};
}

SlicePairs slice_pairs_from_json(const nlohmann::json& j, const std::string& what) {
  try {
    SlicePairs p;
    p.index = j.at("index").get<int>();
    p.black = j.at("black").get<bool>();
    if (!j.at("duplicate_of").is_null()) p.duplicate_of = j.at("duplicate_of").get<int>();
    p.pixel_hash = std::stoull(j.at("pixel_hash").get<std::string>(), nullptr, 16);
    p.quality = j.at("quality").get<double>();
    for (const auto& e : j.at("edges")) {
      PairEdge edge;
      edge.from = e.at("from").get<int>();
      edge.to = e.at("to").get<int>();
      edge.relative = {e.at("rotation_deg").get<double>(), e.at("dx_px").get<double>(),
                       e.at("dy_px").get<double>()};
      edge.weight = e.at("weight").get<double>();
      if (!(edge.weight > 0.0) || edge.to != p.index || edge.from >= edge.to || edge.from < 0)
        throw FormatError("bad edge");
      p.edges.push_back(edge);
    }
    if (j.contains("fiducials")) {
      for (const auto& f : j.at("fiducials")) {
        const cv::Point2d pt(f.at(0).get<double>(), f.at(1).get<double>());
        if (!std::isfinite(pt.x) || !std::isfinite(pt.y)) throw FormatError("bad fiducial");
        p.fiducials.push_back(pt);
      }
    }
    return p;
  } catch (const std::exception& e) {
    throw FormatError(cat(what, ": malformed pair record: ", e.what()));
  }
}

std::vector<SlicePairs> compute_pairs(int first, int last,
                                      const std::function<RegisterFrame(int)>& frame,
                                      const RegisterOptions& options, int threads) {
  std::vector<SlicePairs> out;
  if (last <= first) return out;
  const int lo = std::max(0, first - kLookBack);
  // Frames are prepared in blocks so memory stays bounded by the block (plus the look-back).
  constexpr int kBlock = 32;
  std::map<int, RegisterFrame> frames;
  std::map<int, SlicePairs> status;  // black / duplicate status of every prepared slice
  out.reserve(std::size_t(last - first));
  for (int block = lo; block < last; block += kBlock) {
    const int block_end = std::min(last, block + kBlock);
    std::vector<RegisterFrame> prepared(std::size_t(block_end - block));
    parallel_for(block_end - block, threads,
                 [&](std::int64_t i) { prepared[std::size_t(i)] = frame(block + int(i)); });
    for (int k = block; k < block_end; ++k) {
      RegisterFrame& f = prepared[std::size_t(k - block)];
      SlicePairs s;
      s.index = k;
      s.black = f.black;
      s.pixel_hash = f.pixel_hash;
      s.quality = s.black ? 0.0 : 1.0;
      s.fiducials = f.fiducials;
      if (!s.black) {
        for (int j = k - 1; j >= std::max(0, k - kLookBack); --j) {
          auto it = status.find(j);
          if (it == status.end() || it->second.black) continue;
          if (it->second.pixel_hash == s.pixel_hash && frames.at(j).full_size == f.full_size) {
            s.duplicate_of = it->second.duplicate_of ? *it->second.duplicate_of : j;
            break;
          }
        }
      }
      status[k] = s;
      frames[k] = std::move(f);
    }
    // Edges of the block's slices inside [first, last): first every slice's edge from its
    // previous usable slice (the full search), then the skip edges from the one before, each
    // started from the composition of two measured neighbour edges where there is one.
    struct Job {
      int from, to;
    };
    // The look-back slices before `first` get their nearest edges too (not returned): the
    // skip edges into `first` start from them exactly as in an unsharded run, so shards
    // reproduce the unsharded records.
    std::vector<Job> nearest, skip;
    for (int k = std::max(lo, block); k < block_end; ++k) {
      const SlicePairs& s = status[k];
      if (s.black || s.duplicate_of) continue;
      int found = 0;
      for (int j = k - 1; j >= std::max(lo, k - kLookBack) && found < 2; --j) {
        const SlicePairs& p = status.at(j);
        if (p.black || p.duplicate_of) continue;
        if (found == 0) {
          nearest.push_back({j, k});
        } else if (k >= first) {
          skip.push_back({j, k});
        }
        ++found;
      }
    }
    auto record = [&](const Job& job, const PairEstimate& r) {
      SlicePairs& s = status[job.to];
      const bool is_nearest = s.edges.empty();  // nearest edges are recorded first
      s.edges.push_back({job.from, job.to, r.relative, r.ecc_ok ? 1.0 : 0.05});
      if (is_nearest) s.quality = r.quality;
    };
    std::vector<PairEstimate> results(nearest.size());
    parallel_for(std::int64_t(nearest.size()), threads, [&](std::int64_t i) {
      const Job& job = nearest[std::size_t(i)];
      results[std::size_t(i)] = estimate_pair(frames.at(job.from), frames.at(job.to), options);
    });
    for (std::size_t i = 0; i < nearest.size(); ++i)
      record(nearest[i], results[i]);
    // The measured edge i→k and j→i (i = k's nearest usable predecessor) compose to a start.
    auto composed = [&](const Job& job) -> std::optional<Rigid> {
      const SlicePairs& sk = status.at(job.to);
      if (sk.edges.empty() || sk.edges[0].weight < 1.0) return std::nullopt;
      const int i = sk.edges[0].from;
      auto it = status.find(i);
      if (it == status.end() || it->second.edges.empty()) return std::nullopt;
      const PairEdge& ji = it->second.edges[0];
      if (ji.from != job.from || ji.weight < 1.0) return std::nullopt;
      const cv::Point2d c = image_centre(frames.at(job.to).full_size);
      return rigid_from_matrix(
          compose_affine(rigid_matrix(sk.edges[0].relative, c), rigid_matrix(ji.relative, c)), c);
    };
    results.assign(skip.size(), PairEstimate{});
    parallel_for(std::int64_t(skip.size()), threads, [&](std::int64_t i) {
      const Job& job = skip[std::size_t(i)];
      const std::optional<Rigid> start = composed(job);
      results[std::size_t(i)] =
          estimate_pair(frames.at(job.from), frames.at(job.to), options, start ? &*start : nullptr);
    });
    for (std::size_t i = 0; i < skip.size(); ++i)
      record(skip[i], results[i]);
    for (int k = std::max(first, block); k < block_end; ++k)
      out.push_back(status[k]);
    // Keep only the look-back window of frames.
    while (!frames.empty() && frames.begin()->first < block_end - kLookBack)
      frames.erase(frames.begin());
  }
  return out;
}

namespace {

// Rigid least-squares fit p ≈ M(q) of matched points (at least two).
cv::Matx23d fit_rigid(const std::vector<cv::Point2d>& q, const std::vector<cv::Point2d>& p) {
  cv::Point2d qm(0, 0), pm(0, 0);
  for (std::size_t i = 0; i < q.size(); ++i)
    qm += q[i], pm += p[i];
  qm *= 1.0 / double(q.size());
  pm *= 1.0 / double(p.size());
  double sc = 0, ss = 0;
  for (std::size_t i = 0; i < q.size(); ++i) {
    const cv::Point2d a = q[i] - qm, b = p[i] - pm;
    sc += a.x * b.x + a.y * b.y;
    ss += a.x * b.y - a.y * b.x;
  }
  const double angle = std::atan2(ss, sc), co = std::cos(angle), si = std::sin(angle);
  return {co, -si, pm.x - (co * qm.x - si * qm.y), si, co, pm.y - (si * qm.x + co * qm.y)};
}

cv::Point2d apply(const cv::Matx23d& m, const cv::Point2d& p) {
  return {m(0, 0) * p.x + m(0, 1) * p.y + m(0, 2), m(1, 0) * p.x + m(1, 1) * p.y + m(1, 2)};
}

// Fiducial group edges (see register.h): `t` is the pair-edge-only solution. Returns the edges
// (free nodes numbered from n) and the number of groups.
constexpr double kTrackPx = 4.0;             // a fiducial continues a track within this distance
constexpr int kMinTrackLength = 3;           // tracks seen on fewer slices are ignored
constexpr double kFiducialWeight = 25.0;     // weight of a fiducial edge (a pair edge has 1)
constexpr double kFiducialResidualPx = 1.0;  // largest misfit of one fiducial in a group fit
constexpr double kFiducialAgreePx = 10.0;    // a fit further than this from the chain is dropped

std::vector<PairEdge> fiducial_edges(const std::vector<SlicePairs>& pairs,
                                     const std::vector<Rigid>& t, cv::Size size, int* groups) {
  const int n = int(pairs.size());
  const cv::Point2d c = image_centre(size);
  auto usable = [&](int k) { return !pairs[k].black && !pairs[k].duplicate_of; };
  // Tracks on the output grid, followed slice by slice.
  struct Track {
    cv::Point2d last;
    int length = 0;
  };
  std::vector<Track> tracks;
  std::vector<std::vector<std::pair<int, cv::Point2d>>> seen(
      static_cast<std::size_t>(n));  // (track, p)
  for (int k = 0; k < n; ++k) {
    if (!usable(k)) continue;
    const cv::Matx23d to_output = invert_affine(rigid_matrix(t[std::size_t(k)], c));
    std::vector<bool> taken(tracks.size(), false);
    for (const auto& p : pairs[std::size_t(k)].fiducials) {
      const cv::Point2d q = apply(to_output, p);
      int best = -1;
      double best_d = kTrackPx;
      for (std::size_t i = 0; i < tracks.size(); ++i) {
        const double d = std::hypot(tracks[i].last.x - q.x, tracks[i].last.y - q.y);
        if (!taken[i] && d < best_d) best = int(i), best_d = d;
      }
      if (best < 0) {
        best = int(tracks.size());
        tracks.push_back({q, 0});
        taken.push_back(false);
      }
      taken[std::size_t(best)] = true;
      tracks[std::size_t(best)].last = q;
      ++tracks[std::size_t(best)].length;
      seen[std::size_t(k)].push_back({best, p});
    }
  }
  // Groups: slices seeing the same set (>= 2) of long tracks.
  std::map<std::vector<int>, std::vector<int>> members;
  for (int k = 0; k < n; ++k) {
    std::vector<int> key;
    for (const auto& s : seen[std::size_t(k)])
      if (tracks[std::size_t(s.first)].length >= kMinTrackLength) key.push_back(s.first);
    std::sort(key.begin(), key.end());
    if (key.size() >= 2) members[key].push_back(k);
  }
  std::vector<PairEdge> edges;
  int g = 0;
  for (const auto& [key, slices] : members) {
    if (int(slices.size()) < kMinTrackLength) continue;
    // The group frame: the mean output-grid position of each track over the group.
    std::vector<cv::Point2d> frame(key.size(), cv::Point2d(0, 0));
    auto point_of = [&](int k, int track) {
      for (const auto& s : seen[std::size_t(k)])
        if (s.first == track) return s.second;
      return cv::Point2d();
    };
    for (int k : slices) {
      const cv::Matx23d to_output = invert_affine(rigid_matrix(t[std::size_t(k)], c));
      for (std::size_t i = 0; i < key.size(); ++i)
        frame[i] += apply(to_output, point_of(k, key[i]));
    }
    for (auto& f : frame)
      f *= 1.0 / double(slices.size());
    std::vector<PairEdge> group;
    for (int k : slices) {
      std::vector<cv::Point2d> observed;
      for (int track : key)
        observed.push_back(point_of(k, track));
      const cv::Matx23d fit_m = fit_rigid(frame, observed);
      // Fiducials are rigid: one that moved against the others (debris, a mismatch) shows as
      // a residual of the fit; such a slice gets no fiducial edge.
      double residual = 0.0;
      for (std::size_t i = 0; i < frame.size(); ++i) {
        const cv::Point2d d = apply(fit_m, frame[i]) - observed[i];
        residual = std::max(residual, std::hypot(d.x, d.y));
      }
      if (residual > kFiducialResidualPx) continue;
      const Rigid fit = rigid_from_matrix(fit_m, c);
      // Agreement with the pair chain (the group frame is close to the output grid).
      const cv::Matx23d diff =
          compose_affine(rigid_matrix(fit, c), invert_affine(rigid_matrix(t[std::size_t(k)], c)));
      if (rigid_motion_px(rigid_from_matrix(diff, c), size) > kFiducialAgreePx) continue;
      group.push_back({n + g, k, fit, kFiducialWeight});
    }
    if (group.size() < 2) continue;
    edges.insert(edges.end(), group.begin(), group.end());
    ++g;
  }
  if (groups) *groups = g;
  return edges;
}

}  // namespace

std::vector<SliceTransform> chain_transforms(const std::vector<SlicePairs>& pairs, cv::Size size,
                                             double jump_px, int* fiducial_groups) {
  const int n = int(pairs.size());
  std::vector<PairEdge> edges;
  for (int k = 0; k < n; ++k) {
    if (pairs[k].index != k)
      throw Error(cat("chain_transforms: pair record ", k, " has index ", pairs[k].index));
    for (const auto& e : pairs[k].edges)
      edges.push_back(e);
  }
  std::vector<Rigid> t = solve_chain(n, edges);
  int groups = 0;
  const std::vector<PairEdge> fid = fiducial_edges(pairs, t, size, &groups);
  if (fiducial_groups) *fiducial_groups = groups;
  if (groups > 0) {
    edges.insert(edges.end(), fid.begin(), fid.end());
    t = solve_chain(n, edges, groups);
    t.resize(std::size_t(n));
  }
  std::vector<SliceTransform> out(static_cast<std::size_t>(n));
  auto usable = [&](int k) { return !pairs[k].black && !pairs[k].duplicate_of; };
  for (int k = 0; k < n; ++k) {
    SliceTransform& s = out[std::size_t(k)];
    s.index = k;
    s.black = pairs[k].black;
    s.duplicate_of = pairs[k].duplicate_of;
    s.quality = k == 0 ? 1.0 : pairs[k].quality;
    s.rotation_deg = t[k].rotation_deg;
    s.dx_px = t[k].dx_px;
    s.dy_px = t[k].dy_px;
  }
  // Black slices: interpolate between the nearest usable neighbours.
  for (int k = 0; k < n; ++k) {
    if (!pairs[k].black) continue;
    int a = k - 1, b = k + 1;
    while (a >= 0 && !usable(a))
      --a;
    while (b < n && !usable(b))
      ++b;
    Rigid ra = a >= 0 ? t[a] : (b < n ? t[b] : Rigid{});
    Rigid rb = b < n ? t[b] : ra;
    const double w = (a >= 0 && b < n) ? double(k - a) / double(b - a) : 0.0;
    SliceTransform& s = out[std::size_t(k)];
    s.rotation_deg = ra.rotation_deg + w * (rb.rotation_deg - ra.rotation_deg);
    s.dx_px = ra.dx_px + w * (rb.dx_px - ra.dx_px);
    s.dy_px = ra.dy_px + w * (rb.dy_px - ra.dy_px);
    s.quality = 0.0;
  }
  // Duplicates: the original's transform.
  for (int k = 0; k < n; ++k) {
    if (!pairs[k].duplicate_of) continue;
    const SliceTransform& o = out[std::size_t(*pairs[k].duplicate_of)];
    SliceTransform& s = out[std::size_t(k)];
    s.rotation_deg = o.rotation_deg;
    s.dx_px = o.dx_px;
    s.dy_px = o.dy_px;
    s.quality = o.quality;
  }
  // Jumps: motion from the previous usable slice to k.
  int prev = -1;
  for (int k = 0; k < n; ++k) {
    if (!usable(k)) continue;
    if (prev >= 0) {
      const cv::Point2d c = image_centre(size);
      cv::Matx23d tk = rigid_matrix({out[k].rotation_deg, out[k].dx_px, out[k].dy_px}, c);
      cv::Matx23d tp = rigid_matrix({out[prev].rotation_deg, out[prev].dx_px, out[prev].dy_px}, c);
      Rigid rel = rigid_from_matrix(compose_affine(tk, invert_affine(tp)), c);
      out[k].jump = rigid_motion_px(rel, size) > jump_px;
    }
    prev = k;
  }
  return out;
}

}  // namespace vispack::pipeline

// Fused Euclidean ECC. See register/ecc.h.
#include "vispack/pipeline/register/ecc.h"

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include <opencv2/imgproc.hpp>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "vispack/common/error.h"

namespace vispack::pipeline {
namespace {

cv::Mat blurred_float(const cv::Mat& image, int blur_size) {
  cv::Mat f;
  image.convertTo(f, CV_32F);
  cv::GaussianBlur(f, f, cv::Size(blur_size, blur_size), 0, 0);
  return f;
}

// The sums one ECC update needs, over the template pixels. "In" pixels are those whose nearest
// input pixel exists (OpenCV's warped mask); the others still count where their bilinear
// footprint reaches the input (OpenCV's warped images are not cleared outside the mask).
// j = (∂I/∂θ, ∂I/∂tx, ∂I/∂ty): the warped gradients times the warp's Jacobian.
struct EccSums {
  double n = 0;                              // "in" pixels
  double i = 0, ii = 0;                      // Σ I, Σ I²          ("in")
  double t = 0, tt = 0, ti = 0;              // Σ T, Σ T², Σ T·I   ("in")
  double j[3] = {}, ji[3] = {}, jt[3] = {};  // Σ j, Σ j·I, Σ j·T ("in")
  double ji_out[3] = {};                     // Σ j·I over the other pixels
  double h[6] = {};                          // Σ j jᵀ over all pixels: 00 01 02 11 12 22

  EccSums& operator+=(const EccSums& o) {
    n += o.n, i += o.i, ii += o.ii, t += o.t, tt += o.tt, ti += o.ti;
    for (int a = 0; a < 3; ++a)
      j[a] += o.j[a], ji[a] += o.ji[a], jt[a] += o.jt[a], ji_out[a] += o.ji_out[a];
    for (int a = 0; a < 6; ++a)
      h[a] += o.h[a];
    return *this;
  }
};

// Bilinear sample of `img` at (x0 + ax, y0 + ay), pixels outside taken as 0 (BORDER_CONSTANT).
inline float sample_clipped(const cv::Mat& img, int x0, int y0, float ax, float ay) {
  auto at = [&](int x, int y) -> float {
    return x >= 0 && y >= 0 && x < img.cols && y < img.rows ? img.at<float>(y, x) : 0.f;
  };
  return (1.f - ay) * ((1.f - ax) * at(x0, y0) + ax * at(x0 + 1, y0)) +
         ay * ((1.f - ax) * at(x0, y0 + 1) + ax * at(x0 + 1, y0 + 1));
}

// One template pixel whose bilinear footprint may leave the input (the slow path).
void add_edge_pixel(const cv::Mat& image, const cv::Mat& grad_x, const cv::Mat& grad_y, double sx,
                    double sy, double t, double hat_x, double hat_y, EccSums& r) {
  const double fx = std::floor(sx), fy = std::floor(sy);
  if (fx < -1.0 || fy < -1.0 || fx >= image.cols || fy >= image.rows) return;  // all outside
  const int x0 = int(fx), y0 = int(fy);
  const float ax = float(sx - fx), ay = float(sy - fy);
  const double i = sample_clipped(image, x0, y0, ax, ay);
  const double gx = sample_clipped(grad_x, x0, y0, ax, ay);
  const double gy = sample_clipped(grad_y, x0, y0, ax, ay);
  const double j0 = gx * hat_x + gy * hat_y, j1 = gx, j2 = gy;
  r.h[0] += j0 * j0, r.h[1] += j0 * j1, r.h[2] += j0 * j2;
  r.h[3] += j1 * j1, r.h[4] += j1 * j2, r.h[5] += j2 * j2;
  const double xn = std::floor(sx + 0.5), yn = std::floor(sy + 0.5);
  if (xn >= 0 && yn >= 0 && xn < image.cols && yn < image.rows) {
    r.n += 1;
    r.i += i, r.ii += i * i;
    r.t += t, r.tt += t * t, r.ti += t * i;
    r.j[0] += j0, r.j[1] += j1, r.j[2] += j2;
    r.ji[0] += j0 * i, r.ji[1] += j1 * i, r.ji[2] += j2 * i;
    r.jt[0] += j0 * t, r.jt[1] += j1 * t, r.jt[2] += j2 * t;
  } else {
    r.ji_out[0] += j0 * i, r.ji_out[1] += j1 * i, r.ji_out[2] += j2 * i;
  }
}

// The interior run of row y: the template pixels x in [first, last) whose whole bilinear
// footprint lies inside the input (0 ≤ sx < w − 1 and 0 ≤ sy < h − 1). The source position is
// affine in x, so the run is an interval: solved, then its ends checked with the same double
// arithmetic the loop uses (pixels outside the run take the exact slow path).
std::pair<int, int> interior_run(const cv::Matx23d& m, double bx, double by, int cols, int wi,
                                 int hi) {
  auto inside = [&](int x) {
    const double sx = m(0, 0) * x + bx, sy = m(1, 0) * x + by;
    return sx >= 0.0 && sy >= 0.0 && sx < wi - 1 && sy < hi - 1;
  };
  double lo = 0.0, hi_x = cols;
  auto clip = [&](double a, double b, double upper) {  // 0 <= a x + b < upper
    if (std::abs(a) < 1e-12) {
      if (!(b >= 0.0 && b < upper)) hi_x = lo;
      return;
    }
    double x1 = (0.0 - b) / a, x2 = (upper - b) / a;
    if (x1 > x2) std::swap(x1, x2);
    lo = std::max(lo, x1);
    hi_x = std::min(hi_x, x2);
  };
  clip(m(0, 0), bx, wi - 1);
  clip(m(1, 0), by, hi - 1);
  if (!(hi_x > lo)) return {0, 0};
  int first = int(std::ceil(lo)), last = int(std::floor(hi_x)) + 1;
  first = std::clamp(first, 0, cols);
  last = std::clamp(last, first, cols);
  while (first < last && !inside(first))
    ++first;
  while (last > first && !inside(last - 1))
    --last;
  return {first, last};
}

// Sums over an interior run from its samples: float lanes (kLanes wide, which the compiler
// vectorises) over blocks of kBlock pixels, each block's lane sums added in double.
constexpr int kLanes = 8;
constexpr int kBlock = 512;

void add_interior_run(const float* t, const float* iv, const float* gxv, const float* gyv,
                      const float* hat_x, const float* hat_y, int count, EccSums& r) {
  for (int b0 = 0; b0 < count; b0 += kBlock) {
    const int n = std::min(kBlock, count - b0);
    float acc[20][kLanes] = {};
    int x = 0;
    for (; x + kLanes <= n; x += kLanes) {
      for (int l = 0; l < kLanes; ++l) {
        const int k = b0 + x + l;
        const float i = iv[k], tv = t[k], gx = gxv[k], gy = gyv[k];
        const float j0 = gx * hat_x[k] + gy * hat_y[k];
        acc[0][l] += i;
        acc[1][l] += i * i;
        acc[2][l] += tv;
        acc[3][l] += tv * tv;
        acc[4][l] += tv * i;
        acc[5][l] += j0;
        acc[6][l] += gx;
        acc[7][l] += gy;
        acc[8][l] += j0 * i;
        acc[9][l] += gx * i;
        acc[10][l] += gy * i;
        acc[11][l] += j0 * tv;
        acc[12][l] += gx * tv;
        acc[13][l] += gy * tv;
        acc[14][l] += j0 * j0;
        acc[15][l] += j0 * gx;
        acc[16][l] += j0 * gy;
        acc[17][l] += gx * gx;
        acc[18][l] += gx * gy;
        acc[19][l] += gy * gy;
      }
    }
    double sum[20] = {};
    for (int a = 0; a < 20; ++a)
      for (int l = 0; l < kLanes; ++l)
        sum[a] += acc[a][l];
    for (; x < n; ++x) {  // the block's tail
      const int k = b0 + x;
      const double i = iv[k], tv = t[k], gx = gxv[k], gy = gyv[k];
      const double j0 = double(gx * hat_x[k] + gy * hat_y[k]);
      const double v[20] = {i,       i * i,   tv,      tv * tv, tv * i,  j0,      gx,
                            gy,      j0 * i,  gx * i,  gy * i,  j0 * tv, gx * tv, gy * tv,
                            j0 * j0, j0 * gx, j0 * gy, gx * gx, gx * gy, gy * gy};
      for (int a = 0; a < 20; ++a)
        sum[a] += v[a];
    }
    r.n += n;
    r.i += sum[0], r.ii += sum[1], r.t += sum[2], r.tt += sum[3], r.ti += sum[4];
    for (int a = 0; a < 3; ++a) {
      r.j[a] += sum[5 + a];
      r.ji[a] += sum[8 + a];
      r.jt[a] += sum[11 + a];
    }
    for (int a = 0; a < 6; ++a)
      r.h[a] += sum[14 + a];
  }
}

// The samples of row y's interior run [first, last) (interior_run) into iv, gxv, gyv (the
// input and its gradients, bilinear) and hat_x, hat_y (OpenCV's hatX, hatY), index x − first.
// With SSE2, four pixels at a time with the same operations in the same order as the scalar
// loop (no fused multiply-add), so both give the same bits; the scalar loop does the rest.
void sample_interior_run(const float* img, const float* gxp, const float* gyp, std::size_t step,
                         const cv::Matx23d& m, double bx, double by, int y, int first, int last,
                         float* iv, float* gxv, float* gyv, float* hat_x, float* hat_y) {
  const double h0 = m(0, 0), h1 = m(1, 0);  // cos θ, sin θ
  int x = first;
#if defined(__SSE2__)
  const __m128d vh0 = _mm_set1_pd(h0), vh1 = _mm_set1_pd(h1), vbx = _mm_set1_pd(bx),
                vby = _mm_set1_pd(by), vyh0 = _mm_set1_pd(y * h0), vyh1 = _mm_set1_pd(y * h1),
                sign = _mm_set1_pd(-0.0);
  const __m128 one = _mm_set1_ps(1.f);
  alignas(16) int xi[4], yi[4];
  for (; x + 4 <= last; x += 4) {
    const __m128d xa = _mm_set_pd(x + 1, x), xb = _mm_set_pd(x + 3, x + 2);
    const __m128d sxa = _mm_add_pd(_mm_mul_pd(vh0, xa), vbx);
    const __m128d sxb = _mm_add_pd(_mm_mul_pd(vh0, xb), vbx);
    const __m128d sya = _mm_add_pd(_mm_mul_pd(vh1, xa), vby);
    const __m128d syb = _mm_add_pd(_mm_mul_pd(vh1, xb), vby);
    const __m128i x0a = _mm_cvttpd_epi32(sxa), x0b = _mm_cvttpd_epi32(sxb);
    const __m128i y0a = _mm_cvttpd_epi32(sya), y0b = _mm_cvttpd_epi32(syb);
    const __m128 ax = _mm_movelh_ps(_mm_cvtpd_ps(_mm_sub_pd(sxa, _mm_cvtepi32_pd(x0a))),
                                    _mm_cvtpd_ps(_mm_sub_pd(sxb, _mm_cvtepi32_pd(x0b))));
    const __m128 ay = _mm_movelh_ps(_mm_cvtpd_ps(_mm_sub_pd(sya, _mm_cvtepi32_pd(y0a))),
                                    _mm_cvtpd_ps(_mm_sub_pd(syb, _mm_cvtepi32_pd(y0b))));
    _mm_store_si128(reinterpret_cast<__m128i*>(xi), _mm_unpacklo_epi64(x0a, x0b));
    _mm_store_si128(reinterpret_cast<__m128i*>(yi), _mm_unpacklo_epi64(y0a, y0b));
    std::size_t o[4];
    for (int l = 0; l < 4; ++l)
      o[l] = std::size_t(yi[l]) * step + std::size_t(xi[l]);
    const __m128 nax = _mm_sub_ps(one, ax), nay = _mm_sub_ps(one, ay);
    const __m128 w00 = _mm_mul_ps(nax, nay), w01 = _mm_mul_ps(ax, nay), w10 = _mm_mul_ps(nax, ay),
                 w11 = _mm_mul_ps(ax, ay);
    // Two neighbours of a row at once (8 bytes), regrouped into the four corners' lanes.
    auto sample = [&](const float* p) {
      auto pair = [&](std::size_t a, std::size_t b) {
        return _mm_loadh_pi(_mm_loadl_pi(_mm_setzero_ps(), reinterpret_cast<const __m64*>(p + a)),
                            reinterpret_cast<const __m64*>(p + b));
      };
      const __m128 t01 = pair(o[0], o[1]), t23 = pair(o[2], o[3]);
      const __m128 b01 = pair(o[0] + step, o[1] + step), b23 = pair(o[2] + step, o[3] + step);
      const __m128 a00 = _mm_shuffle_ps(t01, t23, _MM_SHUFFLE(2, 0, 2, 0));
      const __m128 a01 = _mm_shuffle_ps(t01, t23, _MM_SHUFFLE(3, 1, 3, 1));
      const __m128 a10 = _mm_shuffle_ps(b01, b23, _MM_SHUFFLE(2, 0, 2, 0));
      const __m128 a11 = _mm_shuffle_ps(b01, b23, _MM_SHUFFLE(3, 1, 3, 1));
      return _mm_add_ps(
          _mm_add_ps(_mm_add_ps(_mm_mul_ps(w00, a00), _mm_mul_ps(w01, a01)), _mm_mul_ps(w10, a10)),
          _mm_mul_ps(w11, a11));
    };
    const std::size_t k = std::size_t(x - first);
    _mm_storeu_ps(iv + k, sample(img));
    _mm_storeu_ps(gxv + k, sample(gxp));
    _mm_storeu_ps(gyv + k, sample(gyp));
    // hat_x = −(x·h1) − y·h0, hat_y = x·h0 − y·h1 (as the scalar loop), then to float.
    const __m128d hxa = _mm_sub_pd(_mm_xor_pd(_mm_mul_pd(xa, vh1), sign), vyh0);
    const __m128d hxb = _mm_sub_pd(_mm_xor_pd(_mm_mul_pd(xb, vh1), sign), vyh0);
    const __m128d hya = _mm_sub_pd(_mm_mul_pd(xa, vh0), vyh1);
    const __m128d hyb = _mm_sub_pd(_mm_mul_pd(xb, vh0), vyh1);
    _mm_storeu_ps(hat_x + k, _mm_movelh_ps(_mm_cvtpd_ps(hxa), _mm_cvtpd_ps(hxb)));
    _mm_storeu_ps(hat_y + k, _mm_movelh_ps(_mm_cvtpd_ps(hya), _mm_cvtpd_ps(hyb)));
  }
#endif
  for (; x < last; ++x) {
    const double sx = h0 * x + bx, sy = h1 * x + by;
    const int x0 = int(sx), y0 = int(sy);  // non-negative: truncation is floor
    const float ax = float(sx - x0), ay = float(sy - y0);
    const std::size_t o = std::size_t(y0) * step + std::size_t(x0);
    const float w00 = (1.f - ax) * (1.f - ay), w01 = ax * (1.f - ay), w10 = (1.f - ax) * ay,
                w11 = ax * ay;
    const std::size_t k = std::size_t(x - first);
    iv[k] = w00 * img[o] + w01 * img[o + 1] + w10 * img[o + step] + w11 * img[o + step + 1];
    gxv[k] = w00 * gxp[o] + w01 * gxp[o + 1] + w10 * gxp[o + step] + w11 * gxp[o + step + 1];
    gyv[k] = w00 * gyp[o] + w01 * gyp[o + 1] + w10 * gyp[o + step] + w11 * gyp[o + step + 1];
    hat_x[k] = float(-(x * h1) - (y * h0));
    hat_y[k] = float(x * h0 - y * h1);
  }
}

EccSums accumulate(const cv::Mat& tmpl, const cv::Mat& image, const cv::Mat& grad_x,
                   const cv::Mat& grad_y, const cv::Matx23d& m) {
  EccSums s;
  const int wi = image.cols, hi = image.rows, cols = tmpl.cols;
  const double h0 = m(0, 0), h1 = m(1, 0);  // cos θ, sin θ
  const std::size_t step = image.step1();
  const float* img = image.ptr<float>();
  const float* gxp = grad_x.ptr<float>();
  const float* gyp = grad_y.ptr<float>();
  const auto row_size = static_cast<std::size_t>(cols);
  std::vector<float> iv(row_size), gxv(row_size), gyv(row_size), hat_x(row_size), hat_y(row_size);
  for (int y = 0; y < tmpl.rows; ++y) {
    const float* trow = tmpl.ptr<float>(y);
    EccSums r;  // this row's sums (then added: less rounding on large images)
    const double bx = m(0, 1) * y + m(0, 2), by = m(1, 1) * y + m(1, 2);
    // ∂(source)/∂θ dotted with the gradient: OpenCV's hatX, hatY at template pixel (x, y).
    auto hx = [&](int x) { return -(x * h1) - (y * h0); };
    auto hy = [&](int x) { return x * h0 - y * h1; };
    const auto [first, last] = interior_run(m, bx, by, cols, wi, hi);
    for (int x = 0; x < cols; ++x) {
      if (x == first && first < last) {
        x = last - 1;
        continue;
      }
      add_edge_pixel(image, grad_x, grad_y, m(0, 0) * x + bx, m(1, 0) * x + by, trow[x], hx(x),
                     hy(x), r);
    }
    if (last > first)
      sample_interior_run(img, gxp, gyp, step, m, bx, by, y, first, last, iv.data(), gxv.data(),
                          gyv.data(), hat_x.data(), hat_y.data());
    if (last > first)
      add_interior_run(trow + first, iv.data(), gxv.data(), gyv.data(), hat_x.data(), hat_y.data(),
                       last - first, r);
    s += r;
  }
  return s;
}

}  // namespace

std::optional<double> ecc_euclidean(const cv::Mat& tmpl, const cv::Mat& input, cv::Matx23d& warp,
                                    const EccOptions& options) {
  if (tmpl.channels() != 1 || input.channels() != 1 || tmpl.rows < 3 || tmpl.cols < 3 ||
      input.rows < 3 || input.cols < 3)
    throw Error(cat("ecc_euclidean: images must have one channel and be at least 3x3 (template ",
                    tmpl.cols, "x", tmpl.rows, ", input ", input.cols, "x", input.rows, ")"));
  if (options.blur_size < 1 || options.blur_size % 2 == 0)
    throw Error(
        cat("ecc_euclidean: blur size ", options.blur_size, " is not a positive odd number"));
  if (!(options.min_step_px >= 0.0) || !std::isfinite(options.min_step_px))
    throw Error(cat("ecc_euclidean: minimum step ", options.min_step_px,
                    " px is not a finite non-negative number"));
  const cv::Mat t = blurred_float(tmpl, options.blur_size);
  const cv::Mat image = blurred_float(input, options.blur_size);
  // Central differences, the border reflected (OpenCV's filter2D with (-0.5, 0, 0.5)).
  cv::Mat grad_x, grad_y;
  const cv::Matx13f dx(-0.5f, 0.0f, 0.5f);
  cv::filter2D(image, grad_x, -1, dx);
  cv::filter2D(image, grad_y, -1, dx.t());

  // The farthest template pixel from the origin, the rotation's lever in the step bound.
  const double diagonal = std::hypot(t.cols - 1, t.rows - 1);
  cv::Matx23d m = warp;
  double rho = -1.0, last_rho = -options.eps;
  for (int it = 1; it <= options.iterations && std::abs(rho - last_rho) >= options.eps; ++it) {
    const EccSums s = accumulate(t, image, grad_x, grad_y, m);
    if (s.n < 1) return std::nullopt;
    const double mean_i = s.i / s.n, mean_t = s.t / s.n;
    const double img_norm2 = std::max(0.0, s.ii - s.n * mean_i * mean_i);
    const double tmp_norm2 = std::max(0.0, s.tt - s.n * mean_t * mean_t);
    const double correlation = s.ti - s.n * mean_t * mean_i;
    last_rho = rho;
    rho = correlation / std::sqrt(img_norm2 * tmp_norm2);
    if (!std::isfinite(rho)) return std::nullopt;
    const cv::Matx33d hessian(s.h[0], s.h[1], s.h[2], s.h[1], s.h[3], s.h[4], s.h[2], s.h[4],
                              s.h[5]);
    bool invertible = false;
    const cv::Matx33d hessian_inv = hessian.inv(cv::DECOMP_LU, &invertible);
    if (!invertible) return std::nullopt;
    cv::Vec3d image_projection, template_projection;
    for (int a = 0; a < 3; ++a) {
      image_projection[a] = s.ji[a] - mean_i * s.j[a] + s.ji_out[a];
      template_projection[a] = s.jt[a] - mean_t * s.j[a];
    }
    const cv::Vec3d q = hessian_inv * image_projection;
    const double lambda_n = img_norm2 - image_projection.dot(q);
    const double lambda_d = correlation - template_projection.dot(q);
    if (!(lambda_d > 0.0)) return std::nullopt;
    const double lambda = lambda_n / lambda_d;
    const cv::Vec3d delta = hessian_inv * (lambda * template_projection - image_projection);
    if (!std::isfinite(delta[0]) || !std::isfinite(delta[1]) || !std::isfinite(delta[2]))
      return std::nullopt;
    const double theta = delta[0] + std::asin(std::clamp(m(1, 0), -1.0, 1.0));
    m(0, 2) += delta[1];
    m(1, 2) += delta[2];
    m(0, 0) = m(1, 1) = std::cos(theta);
    m(1, 0) = std::sin(theta);
    m(0, 1) = -m(1, 0);
    warp = m;
    if (options.diverged && options.diverged(m)) return std::nullopt;
    if (options.give_up && options.give_up(rho, it)) return std::nullopt;
    if (std::hypot(delta[1], delta[2]) + std::abs(delta[0]) * diagonal < options.min_step_px)
      break;  // converged: this update moved no pixel by min_step_px
  }
  return rho;
}

}  // namespace vispack::pipeline

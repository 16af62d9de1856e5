// The registration's ECC: OpenCV's cv::findTransformECC against vispack's fused iteration
// (register/ecc.h) on the same images, from the same start, with the same settings, one thread,
// interleaved (OpenCV, fused, OpenCV, ...), at the sizes the pipeline runs ECC on for 2048×1216
// slices: the pair's fine level (ecc_scale 0.5: 1024×608, frames pre-blurred, blur 1) and the CT
// anchor's working grid (0.33 / 0.94 mm: 719×427, blur 5 and 3). The images: a smooth textured
// body warped by a known rotation + translation (bicubic); the error of each result is the largest
// corner displacement from that truth, so both are compared at their error. Prints a table
// (docs/BENCHMARKS.md "ECC").
//   build/bin/ecc_bench [--reps R]
// bench-links: vispack_pipeline
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <vector>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "vispack/pipeline/register/ecc.h"

namespace vp = vispack::pipeline;

namespace {

cv::Mat body_texture(cv::Size size, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.f, 1.f);
  cv::Mat acc(size, CV_32F, cv::Scalar(0));
  for (int octave : {32, 8, 2}) {
    cv::Mat small(size.height / octave + 2, size.width / octave + 2, CV_32F);
    for (int y = 0; y < small.rows; ++y)
      for (int x = 0; x < small.cols; ++x)
        small.at<float>(y, x) = noise(rng);
    cv::Mat up;
    cv::resize(small, up, cv::Size(small.cols * octave, small.rows * octave), 0, 0,
               cv::INTER_CUBIC);
    acc += up(cv::Rect(0, 0, size.width, size.height)) / float(octave);
  }
  cv::normalize(acc, acc, 0.2, 1.0, cv::NORM_MINMAX);
  cv::Mat body(size, CV_8U, cv::Scalar(0));
  cv::ellipse(body, cv::Point(size.width / 2, size.height / 2),
              cv::Size(size.width * 2 / 5, size.height * 2 / 5), 0, 0, 360, cv::Scalar(255), -1);
  cv::Mat out(size, CV_32F, cv::Scalar(0.05));
  acc.copyTo(out, body);
  cv::GaussianBlur(out, out, cv::Size(0, 0), 1.0);
  return out;
}

cv::Matx23d rigid(double theta_deg, cv::Point2d d, cv::Point2d c) {
  const double a = theta_deg * 3.14159265358979323846 / 180.0, ca = std::cos(a), sa = std::sin(a);
  return {ca, -sa, c.x - ca * c.x + sa * c.y + d.x, sa, ca, c.y - sa * c.x - ca * c.y + d.y};
}

double corner_error(const cv::Matx23d& a, const cv::Matx23d& b, cv::Size size) {
  double worst = 0;
  for (double x : {0.0, double(size.width - 1)})
    for (double y : {0.0, double(size.height - 1)}) {
      const cv::Vec2d d = a * cv::Vec3d(x, y, 1) - b * cv::Vec3d(x, y, 1);
      worst = std::max(worst, std::hypot(d[0], d[1]));
    }
  return worst;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  int reps = 7;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--reps") && i + 1 < argc) {
      reps = std::max(1, std::atoi(argv[++i]));
    } else {
      std::fprintf(stderr, "usage: ecc_bench [--reps R]\n");
      return std::strcmp(argv[i], "--help") ? 2 : 0;
    }
  }
  cv::setNumThreads(1);  // the pipeline runs one ECC per worker thread
  struct Case {
    const char* what;
    cv::Size size;
    int blur;
  };
  std::printf(
      "| ECC run (one thread) | image | OpenCV ms | fused ms | OpenCV / fused | OpenCV error px | "
      "fused error px |\n");
  std::printf("|---|---|---|---|---|---|---|\n");
  for (const Case& k : {Case{"pair, fine level (ecc_scale 0.5)", {1024, 608}, 1},
                        Case{"CT anchor, working grid, first pass", {719, 427}, 5},
                        Case{"CT anchor, working grid, final pass", {719, 427}, 3}}) {
    const cv::Mat input = body_texture(k.size, 17);
    const cv::Point2d c(0.5 * (k.size.width - 1), 0.5 * (k.size.height - 1));
    const cv::Matx23d truth = rigid(0.6, {2.3, -1.7}, c);
    cv::Mat tmpl;
    cv::warpAffine(input, tmpl, cv::Mat(truth), k.size, cv::INTER_CUBIC | cv::WARP_INVERSE_MAP,
                   cv::BORDER_REFLECT);
    const cv::Matx23d start =
        rigid(0.2, {1.2, -0.4}, c);  // ~1.5 px off, as the coarse steps leave it
    vp::EccOptions o;
    o.iterations = 50;
    o.eps = 1e-5;
    o.blur_size = k.blur;
    std::vector<double> t_cv, t_fused;
    double e_cv = 0, e_fused = 0;
    for (int r = 0; r < reps; ++r) {
      cv::Mat w(2, 3, CV_32F);
      for (int i = 0; i < 6; ++i)
        w.at<float>(i / 3, i % 3) = float(start.val[i]);
      auto t0 = std::chrono::steady_clock::now();
      cv::findTransformECC(
          tmpl, input, w, cv::MOTION_EUCLIDEAN,
          cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, o.iterations, o.eps),
          cv::noArray(), o.blur_size);
      t_cv.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
      cv::Matx23d wcv;
      for (int i = 0; i < 6; ++i)
        wcv.val[i] = w.at<float>(i / 3, i % 3);
      e_cv = corner_error(wcv, truth, k.size);
      cv::Matx23d wf = start;
      t0 = std::chrono::steady_clock::now();
      if (!vp::ecc_euclidean(tmpl, input, wf, o)) {
        std::fprintf(stderr, "ecc_bench: the fused ECC failed on %s\n", k.what);
        return 1;
      }
      t_fused.push_back(
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
      e_fused = corner_error(wf, truth, k.size);
    }
    std::printf("| %s | %dx%d, blur %d | %.1f | %.1f | %.2fx | %.4f | %.4f |\n", k.what,
                k.size.width, k.size.height, k.blur, 1e3 * median(t_cv), 1e3 * median(t_fused),
                median(t_cv) / median(t_fused), e_cv, e_fused);
  }
  return 0;
}

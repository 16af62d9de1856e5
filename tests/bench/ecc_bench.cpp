// The registration's ECC: OpenCV's cv::findTransformECC against vispack's fused iteration
// (register/ecc.h) on the same images, from the same start, with the same settings, one thread,
// interleaved (OpenCV, fused, OpenCV, ...), at the sizes the pipeline runs ECC on for 2048×1216
// slices: the pair's fine level (ecc_scale 0.5: 1024×608, frames pre-blurred, blur 1) and the CT
// anchor's working grid (0.33 / 0.94 mm: 719×427, blur 5 and 3). The images: a smooth textured
// body warped by a known rotation + translation (bicubic); the error of each result is the largest
// corner displacement from that truth, so both are compared at their error. Times: wall (steady
// clock) and CPU (the process's user + system CPU, one thread, so the steadier measure on a
// loaded machine), medians over R repetitions. Prints a Markdown table; --json writes the same
// rows and the load average at the start (scripts/bench.sh; docs/BENCHMARKS.md "ECC").
//   build/bin/ecc_bench [--reps R] [--json OUT]
// bench-links: vispack_pipeline
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <random>
#include <string>
#include <vector>

#include <unistd.h>

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

// CPU seconds (user + system) the process has used so far.
double cpu_seconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return double(t.tv_sec) + 1e-9 * double(t.tv_nsec);
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  int reps = 7;
  std::string json_path;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--reps") && i + 1 < argc) {
      reps = std::max(1, std::atoi(argv[++i]));
    } else if (!std::strcmp(argv[i], "--json") && i + 1 < argc) {
      json_path = argv[++i];
    } else {
      std::fprintf(stderr, "usage: ecc_bench [--reps R] [--json OUT]\n");
      return std::strcmp(argv[i], "--help") ? 2 : 0;
    }
  }
  cv::setNumThreads(1);  // the pipeline runs one ECC per worker thread
  struct Case {
    const char* what;
    cv::Size size;
    int blur;
  };
  double load[3] = {0, 0, 0};
  if (getloadavg(load, 3) != 3) load[0] = load[1] = load[2] = -1;
  std::string rows_json;
  std::printf(
      "| ECC run (one thread) | image | OpenCV ms | fused ms | OpenCV CPU ms | fused CPU ms | "
      "OpenCV / fused (CPU) | OpenCV error px | fused error px |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|\n");
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
    std::vector<double> t_cv, t_fused, c_cv, c_fused;
    double e_cv = 0, e_fused = 0;
    for (int r = 0; r < reps; ++r) {
      cv::Mat w(2, 3, CV_32F);
      for (int i = 0; i < 6; ++i)
        w.at<float>(i / 3, i % 3) = float(start.val[i]);
      auto t0 = std::chrono::steady_clock::now();
      double c0 = cpu_seconds();
      cv::findTransformECC(
          tmpl, input, w, cv::MOTION_EUCLIDEAN,
          cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, o.iterations, o.eps),
          cv::noArray(), o.blur_size);
      t_cv.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
      c_cv.push_back(cpu_seconds() - c0);
      cv::Matx23d wcv;
      for (int i = 0; i < 6; ++i)
        wcv.val[i] = w.at<float>(i / 3, i % 3);
      e_cv = corner_error(wcv, truth, k.size);
      cv::Matx23d wf = start;
      t0 = std::chrono::steady_clock::now();
      c0 = cpu_seconds();
      if (!vp::ecc_euclidean(tmpl, input, wf, o)) {
        std::fprintf(stderr, "ecc_bench: the fused ECC failed on %s\n", k.what);
        return 1;
      }
      t_fused.push_back(
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
      c_fused.push_back(cpu_seconds() - c0);
      e_fused = corner_error(wf, truth, k.size);
    }
    std::printf("| %s | %dx%d, blur %d | %.1f | %.1f | %.1f | %.1f | %.2fx | %.4f | %.4f |\n",
                k.what, k.size.width, k.size.height, k.blur, 1e3 * median(t_cv),
                1e3 * median(t_fused), 1e3 * median(c_cv), 1e3 * median(c_fused),
                median(c_cv) / median(c_fused), e_cv, e_fused);
    char row[512];
    std::snprintf(row, sizeof row,
                  "%s\n    {\"what\": \"%s\", \"width\": %d, \"height\": %d, \"blur\": %d, "
                  "\"opencv_ms\": %.3f, \"fused_ms\": %.3f, \"opencv_cpu_ms\": %.3f, "
                  "\"fused_cpu_ms\": %.3f, \"opencv_error_px\": %.5f, \"fused_error_px\": %.5f}",
                  rows_json.empty() ? "" : ",", k.what, k.size.width, k.size.height, k.blur,
                  1e3 * median(t_cv), 1e3 * median(t_fused), 1e3 * median(c_cv),
                  1e3 * median(c_fused), e_cv, e_fused);
    rows_json += row;
  }
  if (!json_path.empty()) {
    // Written whole to a temporary name, synced, then renamed: complete or not at all.
    const std::string tmp = json_path + ".tmp";
    FILE* out = std::fopen(tmp.c_str(), "w");
    const bool written =
        out &&
        std::fprintf(
            out,
            "{\n  \"command\": \"ecc_bench --reps %d\",\n  \"reps\": %d,\n  \"threads\": 1,"
            "\n  \"load_average\": [%.2f, %.2f, %.2f],\n  \"rows\": [%s\n  ]\n}\n",
            reps, reps, load[0], load[1], load[2], rows_json.c_str()) > 0 &&
        std::fflush(out) == 0 && fsync(fileno(out)) == 0;
    if (out) std::fclose(out);
    if (!written) {
      std::fprintf(stderr, "ecc_bench: cannot write %s\n", tmp.c_str());
      return 1;
    }
    if (std::rename(tmp.c_str(), json_path.c_str()) != 0) {
      std::fprintf(stderr, "ecc_bench: cannot rename %s to %s\n", tmp.c_str(), json_path.c_str());
      return 1;
    }
  }
  return 0;
}

// Registration throughput at the Visible Human size (2048×1216): time per slice pair (frame
// preparation + phase correlation + ECC at ecc_scale) on 1 and 2 threads, with the error
// against a known synthetic motion. Prints a table (docs/BENCHMARKS.md "## Pipeline").
//   build/bin/register_bench [--slices N]
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <vector>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "vispack/common/parallel.h"
#include "vispack/pipeline/register.h"

namespace vp = vispack::pipeline;

namespace {

// A VHP-sized textured body in gel (smooth multi-scale texture).
cv::Mat synthetic_slice(cv::Size size) {
  std::mt19937 rng(42);
  std::normal_distribution<float> noise(0.f, 1.f);
  cv::Mat acc(size, CV_32FC3, cv::Scalar::all(0));
  for (int octave : {64, 16, 4}) {
    cv::Mat small(size.height / octave + 2, size.width / octave + 2, CV_32FC3);
    for (int y = 0; y < small.rows; ++y)
      for (int x = 0; x < small.cols; ++x)
        small.at<cv::Vec3f>(y, x) = {noise(rng), noise(rng), noise(rng)};
    cv::Mat up;
    cv::resize(small, up, size, 0, 0, cv::INTER_CUBIC);
    acc += up;
  }
  cv::normalize(acc, acc, 30, 230, cv::NORM_MINMAX);
  cv::Mat body(size, CV_8U, cv::Scalar(0));
  cv::ellipse(body, {size.width / 2, size.height / 2}, {size.width * 2 / 5, size.height * 2 / 5}, 0,
              0, 360, cv::Scalar(255), -1);
  cv::Mat out(size, CV_8UC3, cv::Scalar(40, 70, 160)), tex;
  acc.convertTo(tex, CV_8UC3);
  tex.copyTo(out, body);
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  int pairs = 8;
  for (int i = 1; i + 1 < argc; ++i)
    if (!std::strcmp(argv[i], "--slices")) pairs = std::max(2, std::atoi(argv[i + 1]));
  const cv::Size size(2048, 1216);
  const cv::Mat base = synthetic_slice(size);
  // Slice k is the base moved by a known drift (sub-pixel shift and small rotation).
  std::vector<vp::Rigid> truth(std::size_t(pairs) + 1);
  std::vector<cv::Mat> slices(truth.size());
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (std::size_t k = 0; k < truth.size(); ++k) {
    truth[k] = k == 0 ? vp::Rigid{} : vp::Rigid{0.3 * u(rng), 3.0 * u(rng), 3.0 * u(rng)};
    cv::warpAffine(base, slices[k], cv::Mat(vp::rigid_matrix(truth[k], vp::image_centre(size))),
                   size, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  }
  vp::RegisterOptions options;
  std::printf("| threads | method | ms/slice (prepare + pair) | RMS error px | max error px |\n");
  std::printf("|---|---|---|---|---|\n");
  for (const char* method : {"phase", "phase+ecc"}) {
    for (int threads : {1, 2}) {
      cv::setNumThreads(1);
      options.method = method;
      const auto t0 = std::chrono::steady_clock::now();
      std::vector<vp::RegisterFrame> frames(truth.size());
      std::vector<vp::PairEstimate> est(static_cast<std::size_t>(pairs));
      vispack::parallel_for(std::int64_t(truth.size()), threads, [&](std::int64_t k) {
        frames[std::size_t(k)] = vp::prepare_frame(slices[std::size_t(k)], options);
      });
      // Each slice k >= 1 against slice 0 (the relative motion is truth[k]).
      vispack::parallel_for(pairs, threads, [&](std::int64_t i) {
        est[std::size_t(i)] = vp::estimate_pair(frames[0], frames[std::size_t(i) + 1], options);
      });
      const double seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      double sum2 = 0, worst = 0;
      for (int i = 0; i < pairs; ++i) {
        const auto& r = est[std::size_t(i)].relative;
        const auto& t = truth[std::size_t(i) + 1];
        // Error as the largest corner displacement of the residual transform.
        vp::Rigid diff{r.rotation_deg - t.rotation_deg, r.dx_px - t.dx_px, r.dy_px - t.dy_px};
        const double e = vp::rigid_motion_px(diff, size);
        sum2 += e * e;
        worst = std::max(worst, e);
      }
      std::printf("| %d | %s | %.1f | %.3f | %.3f |\n", threads, method, 1000.0 * seconds / pairs,
                  std::sqrt(sum2 / pairs), worst);
    }
  }
  return 0;
}

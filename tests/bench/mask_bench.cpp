// Mask throughput at the Visible Human size (2048×1216): the CT mask carried onto the colour grid
// with gel refinement (compute_mask) against the plain colour-threshold baseline (distance to the
// gel colour + opening), on 1 and 2 threads, with the IoU against the synthetic truth.
//   build/bin/mask_bench [--slices N] [--ct-scale S] [--json OUT]
// --ct-scale: output pixels per CT pixel (default 4, a 512×512 CT; 2: the CT 2× coarser).
// --json also writes the rows (median of --reps R runs, default 1) for scripts/bench.sh, with a
// third method (CT mask without the gel refinement) for the speed/accuracy curve. The methods are
// interleaved: each repetition runs every method once.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"

#include "vispack/common/parallel.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/mask/mask.h"

namespace vp = vispack::pipeline;

int main(int argc, char** argv) {
  int slices = 16, reps = 1;
  double scale = 4.0;  // output pixels per CT pixel
  std::string json_out;
  for (int i = 1; i + 1 < argc; ++i) {
    if (!std::strcmp(argv[i], "--slices")) slices = std::max(1, std::atoi(argv[i + 1]));
    if (!std::strcmp(argv[i], "--reps")) reps = std::max(1, std::atoi(argv[i + 1]));
    if (!std::strcmp(argv[i], "--json")) json_out = argv[i + 1];
    if (!std::strcmp(argv[i], "--ct-scale")) scale = std::max(1.0, std::atof(argv[i + 1]));
  }
  nlohmann::json rows = nlohmann::json::array();
  const cv::Size size(2048, 1216);
  const cv::Scalar gel(40, 70, 160);
  // Truth: an ellipse body with a gel notch; translucent gel tint near the edge; two green tubes.
  cv::Mat truth(size, CV_8U, cv::Scalar(0));
  cv::ellipse(truth, {1024, 608}, {800, 480}, 0, 0, 360, cv::Scalar(255), -1);
  cv::rectangle(truth, cv::Rect(1780, 580, 60, 40), cv::Scalar(0), -1);
  cv::Mat rgb(size, CV_8UC3, gel);
  cv::Mat noise(size, CV_8UC3);
  cv::randu(noise, 0, 60);
  cv::Mat tissue(size, CV_8UC3, cv::Scalar(170, 90, 80));
  tissue += noise;
  tissue.copyTo(rgb, truth);
  cv::circle(rgb, {120, 120}, 30, cv::Scalar(40, 200, 60), -1);
  cv::circle(rgb, {1930, 1100}, 30, cv::Scalar(40, 200, 60), -1);
  // CT at `scale` output px per CT px (default 4: 512×512; a square matrix covering the colour
  // frame's width): the body (+40 HU) without the notch, in air.
  const int n_ct = std::max(512, int(std::ceil(size.width / scale)));
  vp::Similarity ct_to_out{scale, 0, 0, 0};
  const cv::Matx23d out_to_ct = vp::invert_affine(vp::similarity_matrix(
      ct_to_out, {(n_ct - 1) / 2.0, (n_ct - 1) / 2.0}, vp::image_centre(size)));
  cv::Mat ct(n_ct, n_ct, CV_32F, cv::Scalar(-1000));
  cv::ellipse(ct, {n_ct / 2, n_ct / 2},
              {int(std::lround(800 / scale)), int(std::lround(480 / scale))}, 0, 0, 360,
              cv::Scalar(40), -1);
  vp::MaskOptions options;
  std::printf("| threads | method | ms/slice (wall × threads) | CPU ms/slice | IoU |\n");
  std::printf("|---|---|---|---|---|\n");
  for (int threads : {1, 2}) {
    cv::setNumThreads(1);
    const int methods = json_out.empty() ? 2 : 3;
    // Interleaved: every repetition runs every method once (baseline, CT mask, ...), so the
    // baseline and vispack see the same load; medians over the repetitions.
    std::vector<std::vector<cv::Mat>> outs(static_cast<std::size_t>(methods),
                                           std::vector<cv::Mat>(static_cast<std::size_t>(slices)));
    std::vector<std::vector<double>> all_times(static_cast<std::size_t>(methods)),
        all_cpu(static_cast<std::size_t>(methods));
    for (int r = 0; r < reps; ++r) {
      for (int method = 0; method < methods; ++method) {
        std::vector<cv::Mat>& out = outs[std::size_t(method)];
        vp::MaskOptions mo = options;
        mo.refine_gel = method != 2;
        const std::clock_t c0 = std::clock();  // process CPU time, all threads
        const auto t0 = std::chrono::steady_clock::now();
        vispack::parallel_for(slices, threads, [&](std::int64_t i) {
          if (method == 0) {
            // Baseline: colour threshold + opening (docs/GOALS.md §6 anchor).
            out[std::size_t(i)] = vp::open_disc(
                vp::non_gel(rgb, cv::Vec3f(40, 70, 160), options.gel_distance), options.opening_px);
          } else {
            out[std::size_t(i)] = vp::compute_mask(rgb, &ct, out_to_ct, mo, 0.33 * 0.33).mask;
          }
        });
        all_times[std::size_t(method)].push_back(
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
        all_cpu[std::size_t(method)].push_back(double(std::clock() - c0) / CLOCKS_PER_SEC);
      }
    }
    for (int method = 0; method < methods; ++method) {
      std::vector<double>& times = all_times[std::size_t(method)];
      std::vector<double>& cpu = all_cpu[std::size_t(method)];
      std::sort(times.begin(), times.end());
      std::sort(cpu.begin(), cpu.end());
      const double seconds = times[times.size() / 2];
      const cv::Mat& m = outs[std::size_t(method)][0];
      const double iou = double(cv::countNonZero(m & truth)) / cv::countNonZero(m | truth);
      const char* name = method == 0   ? "colour threshold + opening (baseline)"
                         : method == 1 ? "CT mask + gel refinement"
                                       : "CT mask, no gel refinement";
      std::printf("| %d | %s | %.1f | %.1f | %.4f |\n", threads, name,
                  1000.0 * seconds / slices * threads, 1000.0 * cpu[cpu.size() / 2] / slices, iou);
      rows.push_back({{"threads", threads},
                      {"method", name},
                      {"baseline", method == 0},
                      {"ms_per_slice_per_thread", 1000.0 * seconds / slices * threads},
                      {"ms_per_slice_wall", 1000.0 * seconds / slices},
                      {"cpu_ms_per_slice", 1000.0 * cpu[cpu.size() / 2] / slices},
                      {"iou", iou}});
    }
  }
  std::printf(
      "(wall × threads: wall time × threads / slices, inflated by other processes on a loaded\n"
      " machine; CPU: process CPU time / slices, what the work itself costs)\n");
  if (!json_out.empty())
    vispack::write_file_atomic(json_out, nlohmann::json{{"width", size.width},
                                                        {"height", size.height},
                                                        {"slices", slices},
                                                        {"reps", reps},
                                                        {"ct_scale", scale},
                                                        {"rows", rows}}
                                             .dump(1));
  return 0;
}

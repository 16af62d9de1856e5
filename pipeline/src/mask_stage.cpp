// The vispack-mask stage driver: per-slice masks, overlays and resampled CT. See mask.h.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <mutex>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/pipeline/mask.h"
#include "vispack/pipeline/mask_stage.h"
#include "vispack/pipeline/opencv_threads.h"
#include "vispack/pipeline/register/ct_anchor.h"
#include "vispack/pipeline/slice_io.h"
#include "vispack/pipeline/transforms.h"
#include "vispack/pipeline/work_layout.h"

namespace vispack::pipeline {
namespace {

namespace fs = std::filesystem;

// The overlay a person inspects, its longer side brought down to `max_px` (block mean; the
// outline stays visible as a yellow tint); 0 = full size.
cv::Mat fit_overlay(const cv::Mat& overlay, int max_px) {
  const int longer = std::max(overlay.cols, overlay.rows);
  if (max_px <= 0 || longer <= max_px) return overlay;
  const double s = double(max_px) / longer;
  cv::Mat small;
  cv::resize(overlay, small,
             cv::Size(std::max(1, int(std::lround(overlay.cols * s))),
                      std::max(1, int(std::lround(overlay.rows * s)))),
             0, 0, cv::INTER_AREA);
  return small;
}

}  // namespace

StageResult run_mask_stage(const Config& config, const StageOptions& options) {
  const StackInputs inputs = read_stack_inputs(config);
  const int n = int(inputs.rgb.size());
  const std::string tpath = transforms_path(config);
  const StackTransforms& st = inputs.transforms;
  StageRun run(config, "mask", n, options,
               {"mask", "ct", "rgb", "work.write_ct", "work.overlay_max_px"}, {tpath});
  ScopedOpenCvThreads opencv_threads(run.threads() > 1 ? 1 : cv::getNumThreads());
  const SliceRange range = run.range();
  std::vector<double> coverage(static_cast<std::size_t>(range.size()), -1.0);
  std::atomic<long long> compute_ns{0};
  std::atomic<int> colour_only{0};
  std::mutex gel_mutex;
  cv::Vec3d gel_sum(0, 0, 0);
  int gel_count = 0;
  parallel_for(range.size(), run.threads(), [&](std::int64_t i) {
    const int k = range.first + int(i);
    // The registered colour is rebuilt from input slice k and transforms.json (a stage input:
    // a new transforms.json reruns every slice).
    const std::string& rgb_path = inputs.rgb[std::size_t(k)].path;
    const int ct_k = config.ct ? k + config.ct->slice_offset : -1;
    const bool has_ct = config.ct && ct_k >= 0 && ct_k < int(inputs.ct.size());
    Fingerprint fp;
    fp.text("mask-v2").file(rgb_path);  // v2: colour from the input slice (issue 12)
    if (has_ct) fp.file(inputs.ct[std::size_t(ct_k)].path);
    const std::string in = fp.str();
    std::vector<std::string> outs = {mask_path(config, k), run.slice_path("overlay", k)};
    const bool write_ct = has_ct && config.work.write_ct;
    if (write_ct) outs.push_back(mask_ct_path(config, k));
    if (run.up_to_date(k, in, outs)) {
      run.skip(k);
      return;
    }
    // A CT copy from an earlier run with work.write_ct must not outlive the slice it shows.
    if (!write_ct) {
      std::error_code ec;
      fs::remove(mask_ct_path(config, k), ec);
    }
    cv::Mat rgb = registered_colour(config, inputs, k);
    std::uint64_t bytes = rgb.total() * rgb.elemSize();
    const CtSlice ct = read_ct_slice(config, inputs, k);
    const cv::Mat& ct_hu = ct.hu;
    if (has_ct) {
      bytes += ct_hu.total() * 2;
    } else {
      ++colour_only;
    }
    const auto t0 = std::chrono::steady_clock::now();
    // A black (lost) colour slice has no colour to refine with: its mask is the CT's alone.
    MaskOptions mask_options = config.mask;
    if (st.slices[std::size_t(k)].black) mask_options.refine_gel = false;
    MaskSlice m = compute_mask(rgb, has_ct ? &ct_hu : nullptr, ct.out_to_ct, mask_options);
    compute_ns +=
        std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - t0)
            .count();
    write_image(outs[0], m.mask);
    write_image(outs[1], fit_overlay(draw_mask_overlay(rgb, m.mask), config.work.overlay_max_px));
    if (write_ct) write_image(outs[2], resampled_ct16(config, inputs, k, &ct));
    coverage[std::size_t(i)] = m.coverage;
    {
      std::lock_guard<std::mutex> lock(gel_mutex);
      gel_sum += cv::Vec3d(m.gel[0], m.gel[1], m.gel[2]);
      ++gel_count;
    }
    run.done(k, in, outs, bytes);
  });
  nlohmann::json per = nlohmann::json::object();
  double sum = 0;
  int counted = 0;
  for (int i = 0; i < range.size(); ++i) {
    if (coverage[std::size_t(i)] < 0) continue;
    per[std::to_string(range.first + i)] = coverage[std::size_t(i)];
    sum += coverage[std::size_t(i)], ++counted;
  }
  run.set_quality("coverage", per);
  run.set_quality("mean_coverage", counted ? sum / counted : 0.0);
  run.set_quality("colour_only_slices", colour_only.load());
  if (gel_count > 0)
    run.set_quality("mean_gel_colour",
                    {gel_sum[0] / gel_count, gel_sum[1] / gel_count, gel_sum[2] / gel_count});
  if (counted > 0) run.set_report("mask_ms_per_slice", compute_ns.load() / 1e6 / counted);
  return run.finish();
}

}  // namespace vispack::pipeline

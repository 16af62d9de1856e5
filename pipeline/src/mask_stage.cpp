// The vispack-mask stage driver: per-slice masks, overlays and resampled CT. See mask.h.
#include <algorithm>
#include <atomic>
#include <chrono>
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

}  // namespace

StageResult run_mask_stage(const Config& config, const StageOptions& options) {
  const std::vector<SliceFile> files = stack_slices(config);
  const int n = int(files.size());
  const std::string tpath = transforms_path(config);
  const StackTransforms st = read_stack_transforms(config, n);
  std::vector<SliceFile> ct_files;
  if (config.ct) ct_files = list_slices(*config.ct);
  StageRun run(config, "mask", n, options, {"mask", "ct"}, {tpath});
  ScopedOpenCvThreads opencv_threads(run.threads() > 1 ? 1 : cv::getNumThreads());
  const SliceRange range = run.range();
  std::vector<double> coverage(static_cast<std::size_t>(range.size()), -1.0);
  std::atomic<long long> compute_ns{0};
  std::atomic<int> colour_only{0};
  std::mutex gel_mutex;
  cv::Vec3d gel_sum(0, 0, 0);
  int gel_count = 0;
  const cv::Size size(st.width, st.height);
  parallel_for(range.size(), run.threads(), [&](std::int64_t i) {
    const int k = range.first + int(i);
    const std::string rgb_path = registered_rgb_path(config, k);
    const int ct_k = config.ct ? k + config.ct->slice_offset : -1;
    const bool has_ct = config.ct && ct_k >= 0 && ct_k < int(ct_files.size());
    Fingerprint fp;
    fp.file(rgb_path);
    if (has_ct) fp.file(ct_files[std::size_t(ct_k)].path);
    const std::string in = fp.str();
    std::vector<std::string> outs = {mask_path(config, k), run.slice_path("overlay", k)};
    if (has_ct) outs.push_back(mask_ct_path(config, k));
    if (run.up_to_date(k, in, outs)) {
      run.skip(k);
      return;
    }
    if (!fs::exists(rgb_path))
      throw InputError(cat(rgb_path, ": missing; run vispack-register for slice ", k));
    cv::Mat rgb = read_slice(rgb_path);
    std::uint64_t bytes = rgb.total() * rgb.elemSize();
    if (rgb.depth() == CV_16U) rgb.convertTo(rgb, CV_8U, 255.0 / 65535.0);
    if (rgb.channels() == 1) cv::cvtColor(rgb, rgb, cv::COLOR_GRAY2RGB);
    if (rgb.size() != size)
      throw InputError(cat(rgb_path, ": is ", rgb.cols, "x", rgb.rows, ", transforms.json says ",
                           size.width, "x", size.height));
    cv::Mat ct_hu;
    cv::Matx23d out_to_ct(1, 0, 0, 0, 1, 0);
    if (has_ct) {
      const std::string& ct_path = ct_files[std::size_t(ct_k)].path;
      cv::Mat raw = read_slice(ct_path, config.ct->raw);
      if (raw.channels() != 1) throw InputError(cat(ct_path, ": CT slice must be single-channel"));
      bytes += raw.total() * raw.elemSize();
      raw.convertTo(ct_hu, CV_32F, config.ct->slope, config.ct->intercept);
      const Similarity c = st.ct_to_rgb ? *st.ct_to_rgb : defined_ct_to_rgb(config);
      out_to_ct = output_to_ct(c, st.centre(), image_centre(ct_hu.size()));
    } else {
      ++colour_only;
    }
    const auto t0 = std::chrono::steady_clock::now();
    // A black (lost) colour slice has no colour to refine with: its mask is the CT's alone.
    MaskOptions mask_options = config.mask;
    if (st.slices[std::size_t(k)].black) mask_options.refine_gel = false;
    MaskSlice m = compute_mask(rgb, has_ct ? &ct_hu : nullptr, out_to_ct, mask_options);
    compute_ns +=
        std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - t0)
            .count();
    write_image(outs[0], m.mask);
    write_image(outs[1], draw_mask_overlay(rgb, m.mask));
    if (has_ct) write_image(outs[2], encode_hu16(resample_ct(ct_hu, out_to_ct, size)));
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

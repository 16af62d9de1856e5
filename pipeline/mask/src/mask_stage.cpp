// The vispack-mask stage driver: per-slice masks, overlays and resampled CT. See mask.h.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <mutex>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/intermediates.h"
#include "vispack/pipeline/imaging/opencv_threads.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/mask/mask.h"
#include "vispack/pipeline/mask/mask_stage.h"

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

MaskStageJob::MaskStageJob(const Config& config, const StackInputs& inputs,
                           const StageOptions& options)
    : config_(config),
      inputs_(inputs),
      run_(config, "mask", int(inputs.rgb.size()), options,
           {"mask", "ct", "rgb", "work.write_ct", "work.overlay_max_px"},
           {transforms_path(config)}) {
  coverage_.assign(static_cast<std::size_t>(run_.range().size()), -1.0);
  parts_.assign(coverage_.size(), PartCounts{});
  colour_only_slice_.assign(static_cast<std::size_t>(run_.range().size()), 0);
}

std::string MaskStageJob::input_fingerprint(int k) const {
  // The registered colour is rebuilt from input slice k and transforms.json (a stage input:
  // a new transforms.json reruns every slice).
  const CtAtZ at =
      ct_at_colour_slice(config_, int(inputs_.ct.size()), inputs_.rgb[std::size_t(k)].slot);
  Fingerprint fp;
  // v2: colour from the input slice; v3: every body part; v4: continuity along z, elongated
  // parts of soft tissue (docs/ARCHITECTURE.md, 'The body mask: every part is body').
  fp.text("mask-v4").file(inputs_.rgb[std::size_t(k)].path);
  if (at.inside()) fp.file(inputs_.ct[std::size_t(at.below)].path);
  // v4: the part rule's continuity along z reads the CT slices beside an exact one.
  if (at.inside() && at.exact())
    for (int j : {at.below - 1, at.below + 1})
      if (j >= 0 && j < int(inputs_.ct.size())) fp.text("z").file(inputs_.ct[std::size_t(j)].path);
  if (at.inside() && !at.exact())
    fp.text("above").number(at.w_above).file(inputs_.ct[std::size_t(at.above)].path);
  // The colour-only mask's edge at the half-covered level; between CT slices the outlines'
  // union trimmed by the colour, or by shape (mask.h): a CT slice's own mask is unchanged.
  if (!at.inside() || !at.exact()) fp.text("edge-v2");
  return fp.str();
}

std::vector<std::string> MaskStageJob::outputs(int k) const {
  std::vector<std::string> outs = {mask_path(config_, k), run_.slice_path("overlay", k)};
  const bool has_ct =
      ct_at_colour_slice(config_, int(inputs_.ct.size()), inputs_.rgb[std::size_t(k)].slot)
          .inside();
  if (has_ct && config_.work.write_ct) outs.push_back(mask_ct_path(config_, k));
  return outs;
}

bool MaskStageJob::up_to_date(int k) const {
  return run_.up_to_date(k, input_fingerprint(k), outputs(k));
}

cv::Mat MaskStageJob::compute(int k, const cv::Mat& rgb, const CtSlice& ct, cv::Mat* ct16) {
  const std::string in = input_fingerprint(k);
  const std::vector<std::string> outs = outputs(k);
  // At a body's tip between two CT slices the colour alone (CtSlice::body_ends); a black colour
  // slice has no colour: the CT's blend there.
  const bool black = inputs_.transforms.slices[std::size_t(k)].black;
  const bool tip = ct.body_ends && !black;
  const bool has_ct = !ct.hu.empty() && !tip;
  const bool write_ct = outs.size() > 2;
  // A CT copy from an earlier run with work.write_ct must not outlive the slice it shows.
  if (!write_ct) {
    std::error_code ec;
    fs::remove(mask_ct_path(config_, k), ec);
  }
  std::uint64_t bytes = rgb.total() * rgb.elemSize();
  // Between two CT slices that show one body: their outlines' union for the colour to trim, or
  // without refinement the outline interpolated by shape (CtSlice::envelope_hu, shape_hu).
  const bool refine = config_.mask.refine_gel && !black;
  const cv::Mat& ct_hu = ct.shape_hu.empty() ? ct.hu : refine ? ct.envelope_hu : ct.shape_hu;
  if (has_ct) {
    bytes += ct_hu.total() * 2;
  } else {
    ++colour_only_;
    colour_only_slice_[std::size_t(k - run_.range().first)] = tip ? 2 : 1;
  }
  const auto t0 = std::chrono::steady_clock::now();
  // A black (lost) colour slice has no colour to refine with: its mask is the CT's alone.
  MaskOptions mask_options = config_.mask;
  if (black) mask_options.refine_gel = false;
  MaskSlice m = compute_mask(rgb, has_ct ? &ct_hu : nullptr, ct.out_to_ct, mask_options,
                             config_.spacing_mm[0] * config_.spacing_mm[1], &ct.z);
  compute_ns_ +=
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - t0)
          .count();
  write_work_image(outs[0], m.mask);
  write_work_image(outs[1],
                   fit_overlay(draw_mask_overlay(rgb, m.mask), config_.work.overlay_max_px),
                   WorkImageContent::kPicture);
  if (write_ct || (ct16 && config_.ct)) {
    cv::Mat resampled = resampled_ct16(config_, inputs_, k, &ct);
    if (write_ct) write_work_image(outs[2], resampled);
    if (ct16) *ct16 = resampled;
  }
  coverage_[std::size_t(k - run_.range().first)] = m.coverage;
  parts_[std::size_t(k - run_.range().first)] = m.parts;
  {
    std::lock_guard<std::mutex> lock(gel_mutex_);
    gel_sum_ += cv::Vec3d(m.gel[0], m.gel[1], m.gel[2]);
    ++gel_count_;
  }
  run_.done(k, in, outs, bytes);
  return m.mask;
}

StageResult MaskStageJob::finish() {
  const SliceRange range = run_.range();
  nlohmann::json per = nlohmann::json::object(), parts = nlohmann::json::object();
  double sum = 0;
  int counted = 0, removed = 0;
  for (int i = 0; i < range.size(); ++i) {
    if (coverage_[std::size_t(i)] < 0) continue;
    const std::string key = std::to_string(range.first + i);
    per[key] = coverage_[std::size_t(i)];
    const PartCounts& p = parts_[std::size_t(i)];
    parts[key] = {{"kept", p.kept}, {"removed", p.removed}};
    removed += p.removed;
    sum += coverage_[std::size_t(i)], ++counted;
  }
  run_.set_quality("coverage", per);
  // The part rule per slice (outline.h): body parts kept, and parts removed as debris, holder
  // or table (or, colour-only, not tissue-coloured).
  run_.set_quality("parts", parts);
  run_.set_quality("parts_removed", removed);
  run_.set_quality("mean_coverage", counted ? sum / counted : 0.0);
  run_.set_quality("colour_only_slices", colour_only_.load());
  std::string colour_only;  // how many slices had no CT, and why
  if (config_.ct) {
    // Slices of this run whose z lies outside the CT's z range: no CT, a colour-only mask.
    std::vector<int> outside, tips;
    for (int i = 0; i < range.size(); ++i) {
      if (colour_only_slice_[std::size_t(i)] == 1) outside.push_back(range.first + i);
      if (colour_only_slice_[std::size_t(i)] == 2) tips.push_back(range.first + i);
    }
    run_.set_quality("outside_ct_slices", outside);
    // Between two CT slices that do not show one body (a body's tip): colour-only masks.
    run_.set_quality("body_tip_slices", tips);
    if (!outside.empty() || !tips.empty())
      colour_only = cat(outside.size() + tips.size(), " slices have a colour-only mask (",
                        outside.size(), " outside the CT's z range, ", tips.size(),
                        " at a body's tip between a CT slice with body and one without)");
  }
  if (gel_count_ > 0)
    run_.set_quality("mean_gel_colour", {gel_sum_[0] / gel_count_, gel_sum_[1] / gel_count_,
                                         gel_sum_[2] / gel_count_});
  if (counted > 0) run_.set_report("mask_ms_per_slice", compute_ns_.load() / 1e6 / counted);
  // A stack with no body at all is a config mistake far more often than a volume of gel
  // (printed even with --quiet: it changes what the output means).
  nlohmann::json warnings = nlohmann::json::array();
  if (counted > 0 && sum == 0.0)
    warnings.push_back(
        cat("no body in any of the ", counted, " slices computed (every mask is empty): check ",
            config_.ct ? "ct.slope, ct.intercept, " : "", "mask.hu_threshold and rgb.raw"));
  if (!colour_only.empty()) warnings.push_back(colour_only);
  for (const auto& w : warnings)
    std::fprintf(stderr, "vispack-mask: warning: %s\n", w.get<std::string>().c_str());
  run_.set_report("warnings", warnings);
  return run_.finish();
}

StageResult run_mask_stage(const Config& config, const StageOptions& options) {
  const StackInputs inputs = read_stack_inputs(config);
  MaskStageJob job(config, inputs, options);
  StageRun& run = job.run();
  // The stage spreads slices over run.threads() workers: OpenCV's own pool stays off (with
  // --threads 1 too, so that one thread means one core, as a SLURM task of one CPU expects).
  ScopedOpenCvThreads opencv_threads(1);
  const SliceRange range = run.range();
  // The slices in flight (one per thread) and the CT slices beside them.
  CtHuCache ct_cache(std::size_t(3 * run.threads() + 4));
  parallel_for(range.size(), run.threads(), [&](std::int64_t i) {
    const int k = range.first + int(i);
    if (job.up_to_date(k)) {
      job.skip(k);
      return;
    }
    const cv::Mat rgb = registered_colour(config, inputs, k);
    job.compute(k, rgb, read_ct_slice(config, inputs, k, /*for_mask=*/true, &ct_cache));
  });
  return job.finish();
}

}  // namespace vispack::pipeline

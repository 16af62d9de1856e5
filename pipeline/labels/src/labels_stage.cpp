// The labels stage (labels_stage.h): each colour slice's segmentation slice mapped to label IDs
// and resampled onto the output grid.
#include "vispack/pipeline/labels/labels_stage.h"

#include <filesystem>
#include <set>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/opencv_threads.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/labels/labels.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;
using nlohmann::json;

void check_seg_numbers_match(const Config& config, const std::vector<SliceFile>& stack,
                             const std::vector<SliceFile>& seg_files) {
  // Matched by file number: a segmentation of fewer slices than half the colour stack's is a
  // stack at another spacing, never to be paired by number (slice_z.h).
  std::set<std::pair<int, int>> numbers;
  for (const auto& f : seg_files)
    numbers.insert({f.number, f.letter});
  int matched = 0;
  for (const auto& f : stack)
    matched += numbers.count({f.number, f.letter}) ? 1 : 0;
  const int n = int(stack.size());
  if (n > 1 && 2 * matched < n)
    throw ConfigError(cat(config.path, ": seg: ", numbers.size(), " slices, of which ", matched,
                          " match the number of one of the colour stack's ", n,
                          " slices; set seg.slice_spacing_mm (and seg.z_offset_mm) to place "
                          "them along z"));
}

LabelsStageJob::LabelsStageJob(const Config& config, const StageOptions& options)
    : config_(config) {
  if (!config.seg)
    throw ConfigError(cat(config.path, ": seg: not configured (no segmentation to map)"));
  const SegSource& seg = *config.seg;
  stack_ = stack_slices(config);
  if (seg.slice_spacing_mm) {
    // Each colour slice takes the segmentation slice nearest in z (slice_z.h; docs/ARCHITECTURE.md,
    // 'Each input at its own z').
    seg_files_ = list_slices(seg);
    check_no_missing_slice(seg, seg_files_, "segmentation");
  } else {
    const std::vector<SliceFile> seg_files = list_slices(seg);
    check_seg_numbers_match(config, stack_, seg_files);
    for (const auto& f : seg_files)
      seg_by_number_[{f.number, f.letter}] = f.path;
  }

  // Transforms: from the register stage, or identities when registration is disabled.
  tpath_ = transforms_path(config);
  have_transforms_ = fs::exists(tpath_);
  if (have_transforms_) {
    transforms_ = read_stack_transforms(config, int(stack_.size()));
  } else if (config.registration.enabled) {
    throw InputError(cat(tpath_, ": missing; run vispack-register first"));
  }

  std::vector<std::string> stage_inputs = {tpath_};
  if (!seg.palette.empty()) stage_inputs.push_back(seg.palette);
  if (!seg.id_map.empty()) stage_inputs.push_back(seg.id_map);
  run_ =
      std::make_unique<StageRun>(config, "labels", int(stack_.size()), options,
                                 std::vector<std::string>{"seg", "rgb", "register"}, stage_inputs);

  if (!seg.palette.empty()) palette_ = read_palette(seg.palette);
  if (seg.mode == "colour") matcher_ = std::make_unique<ColourMatcher>(palette_, seg.tolerance);
  if (!seg.id_map.empty()) id_map_ = read_id_map(seg.id_map);
}

std::string LabelsStageJob::seg_path(int k) const {
  if (config_.seg->slice_spacing_mm) {
    const int seg_j =
        seg_at_colour_slice(config_, int(seg_files_.size()), stack_[std::size_t(k)].slot);
    return seg_j < 0 ? "" : seg_files_[std::size_t(seg_j)].path;
  }
  const SliceFile& colour = stack_[std::size_t(k)];
  auto it = seg_by_number_.find({colour.number, colour.letter});
  return it == seg_by_number_.end() ? "" : it->second;
}

int LabelsStageJob::seg_grid_slice(int k) const {
  if (!config_.seg->slice_spacing_mm) return k;
  const int seg_j =
      seg_at_colour_slice(config_, int(seg_files_.size()), stack_[std::size_t(k)].slot);
  return seg_j < 0 ? k : colour_slice_of_seg(config_, stack_, seg_j);
}

std::string LabelsStageJob::input_fingerprint(int k) const {
  const std::string path = seg_path(k);
  Fingerprint fp;
  fp.text(path.empty() ? "no-seg" : "seg").file(path).file(stack_[std::size_t(k)].path);
  if (config_.seg->slice_spacing_mm) fp.text("grid").number(seg_grid_slice(k));
  return fp.str();
}

bool LabelsStageJob::up_to_date(int k) const {
  return run_->up_to_date(k, input_fingerprint(k), {run_->slice_path("labels", k)});
}

cv::Mat LabelsStageJob::compute(int k) {
  const SegSource& seg = *config_.seg;
  const std::string path = seg_path(k);
  const std::string in = input_fingerprint(k);
  const std::string out_path = run_->slice_path("labels", k);
  SliceTransform t;
  std::array<double, 2> center{};
  cv::Size out_size;
  if (have_transforms_) {
    t = transforms_.slices[std::size_t(seg_grid_slice(k))];
    center = transforms_.center_px;
    out_size = cv::Size(transforms_.width, transforms_.height);
  }
  cv::Mat out;
  LabelStats stats;
  std::uint64_t bytes = 0;
  if (path.empty()) {
    if (!have_transforms_) {
      cv::Mat rgb = read_slice(stack_[std::size_t(k)].path, config_.rgb.raw);
      out_size = rgb.size();
    }
    out = cv::Mat(out_size, CV_16UC1, cv::Scalar(0));
    std::lock_guard<std::mutex> lock(mutex_);
    missing_seg_.push_back(k);
  } else {
    cv::Mat image = read_slice(path, seg.raw);
    bytes = image.total() * image.elemSize();
    if (!have_transforms_) {
      out_size = image.size();
      center = {(image.cols - 1) / 2.0, (image.rows - 1) / 2.0};
    }
    if (image.size() != out_size)
      throw InputError(cat(path, ": is ", image.cols, "x", image.rows,
                           " but the colour slices are ", out_size.width, "x", out_size.height));
    cv::Mat ids = seg.mode == "colour" ? map_colours(image, *matcher_, seg.strict, path, &stats)
                                       : map_ids(image, id_map_.empty() ? nullptr : &id_map_,
                                                 seg.strict, path, &stats);
    out = have_transforms_ ? resample_labels_nearest(ids, t, center, out_size) : ids;
  }
  std::vector<std::uint8_t> id_seen(65536, 0);  // indexed by label ID
  for (int y = 0; y < out.rows; ++y) {
    const std::uint16_t* row = out.ptr<std::uint16_t>(y);
    for (int x = 0; x < out.cols; ++x)
      id_seen[row[x]] = 1;
  }
  std::vector<std::uint16_t> ids_here;
  for (std::size_t id = 1; id < id_seen.size(); ++id)
    if (id_seen[id]) ids_here.push_back(std::uint16_t(id));
  write_work_image(out_path, out);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& u : stats.first_unmatched)
      if (first_.size() < LabelStats::kMaxReported)
        first_.push_back({{"slice", k},
                          {"file", path},
                          {"x", u.x},
                          {"y", u.y},
                          {"value", u.value},
                          {"distance", u.distance}});
    total_.merge(stats);
    present_.insert(ids_here.begin(), ids_here.end());
    if (stats.unmatched) unmatched_by_slice_[k] = stats.unmatched;
  }
  run_->done(k, in, {out_path}, bytes);
  return out;
}

StageResult LabelsStageJob::finish() {
  std::sort(missing_seg_.begin(), missing_seg_.end());
  json by_slice = json::object();
  for (auto& [k, n] : unmatched_by_slice_)
    by_slice[std::to_string(k)] = n;
  const LabelStats& total = total_;
  std::uint64_t all = total.exact + total.nearest + total.unmatched;
  StageRun& run = *run_;
  run.set_quality("pixels_exact", total.exact);
  run.set_quality("pixels_nearest", total.nearest);
  run.set_quality("pixels_unmatched", total.unmatched);
  run.set_quality("fraction_exact", all ? double(total.exact) / all : 1.0);
  run.set_quality("first_unmatched", first_);
  run.set_quality("unmatched_by_slice", by_slice);
  run.set_report("mode", config_.seg->mode);
  run.set_report("palette_entries", palette_.size());
  run.set_report("ids_present", std::vector<std::uint16_t>(present_.begin(), present_.end()));
  run.set_report("missing_seg", missing_seg_);
  run.set_report("transforms", have_transforms_ ? tpath_ : "identity (register.enabled = false)");
  return run.finish(run.dir());
}

StageResult run_labels_stage(const Config& config, const StageOptions& options) {
  LabelsStageJob job(config, options);
  // Slices spread over the stage's workers; OpenCV's pool off (--threads 1 = one core).
  ScopedOpenCvThreads opencv_threads(1);
  const SliceRange range = job.run().range();
  parallel_for(range.size(), job.run().threads(), [&](std::int64_t i) {
    const int k = range.first + int(i);
    if (job.up_to_date(k)) {
      job.skip(k);
      return;
    }
    job.compute(k);
  });
  return job.finish();
}

}  // namespace vispack::pipeline

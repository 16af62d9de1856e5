// The labels stage (vispack-labels): segmentation slices -> label slices on the output grid
// (the matching and resampling are labels.h). Not thread-safe: run one stage at a time per
// process.
#pragma once

#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/labels/labels.h"

namespace vispack::pipeline {

// The stage: seg slices -> work/labels/labels_NNNN.png. Needs config.seg (throws ConfigError
// "seg: not configured" otherwise). Depends on config sections "seg" and "rgb" and on
// transforms.json (identity transforms when registration has not run and register.enabled is
// false). Throws InputError (unmatched colour in strict mode, seg slice of the wrong size).
StageResult run_labels_stage(const Config& config, const StageOptions& options);

// Without seg.slice_spacing_mm segmentation slices pair with colour slices by file number:
// throws ConfigError (naming seg.slice_spacing_mm) when fewer than half of the colour `stack`'s
// slices find a segmentation slice of their number (a stack at another spacing).
void check_seg_numbers_match(const Config& config, const std::vector<SliceFile>& stack,
                             const std::vector<SliceFile>& seg_files);

// The labels stage slice by slice: run_labels_stage and the streaming vispack-run (stream.h)
// share it (same files, same manifest records, same report).
// Thread-safety: up_to_date, skip and compute may be called concurrently for different slices;
// the constructor and finish() from one thread. Throws as run_labels_stage.
class LabelsStageJob {
 public:
  LabelsStageJob(const Config& config, const StageOptions& options);
  LabelsStageJob(const LabelsStageJob&) = delete;
  LabelsStageJob& operator=(const LabelsStageJob&) = delete;

  StageRun& run() { return *run_; }
  bool up_to_date(int k) const;
  void skip(int k) { run_->skip(k); }
  // Reads seg slice k, maps and resamples it, writes work/labels/labels_NNNN.png, records the
  // slice and returns the label slice (CV_16UC1, output grid).
  cv::Mat compute(int k);
  StageResult finish();

 private:
  std::string seg_path(int k) const;
  // The colour slice whose observed grid the segmentation of slice k was drawn on (its
  // transform carries it to the output grid): k itself when segmentation slices are matched by
  // number, else the colour slice nearest the segmentation slice's z (slice_z.h).
  int seg_grid_slice(int k) const;
  std::string input_fingerprint(int k) const;
  const Config& config_;
  std::vector<SliceFile> stack_;
  // Without seg.slice_spacing_mm: by (number, letter) of the file name (slice_io.h).
  std::map<std::pair<int, int>, std::string> seg_by_number_;
  std::vector<SliceFile> seg_files_;  // with seg.slice_spacing_mm: the stack along z
  std::string tpath_;
  StackTransforms transforms_;
  bool have_transforms_ = false;
  std::unique_ptr<StageRun> run_;
  std::vector<PaletteEntry> palette_;
  std::unique_ptr<ColourMatcher> matcher_;
  std::unordered_map<std::uint32_t, std::uint16_t> id_map_;
  std::mutex mutex_;
  LabelStats total_;
  std::vector<int> missing_seg_;
  std::set<std::uint16_t> present_;
  std::map<int, std::uint64_t> unmatched_by_slice_;
  nlohmann::json first_ = nlohmann::json::array();
};

}  // namespace vispack::pipeline

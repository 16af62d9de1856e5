// The mask stage (vispack-mask): the body masks of the whole stack (the algorithm is mask.h).
// Not thread-safe: a stage run sets OpenCV's process-wide thread count for its duration; run one
// stage at a time per process.
#pragma once

#include <atomic>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/intermediates.h"
#include "vispack/pipeline/imaging/outline.h"

namespace vispack::pipeline {

// vispack-mask: for every output slice writes <work>/mask/mask_NNNN.png, overlay_NNNN.png,
// ct_NNNN.png (when CT is configured) and report.json (per-slice coverage, time, throughput).
// Reads <work>/register/transforms.json and the registered slices (run vispack-register first);
// per-slice work, so --slices shards freely.
StageResult run_mask_stage(const Config& config, const StageOptions& options);

// The mask stage slice by slice: run_mask_stage and the streaming vispack-run (stream.h) share
// it, so both write the same files and the same manifest records (a streaming run's masks are up
// to date for a later vispack-mask, and the other way round).
// Thread-safety: up_to_date, skip and compute may be called concurrently for different slices;
// the constructor and finish() from one thread. `inputs` must outlive the job.
class MaskStageJob {
 public:
  MaskStageJob(const Config& config, const StackInputs& inputs, const StageOptions& options);
  MaskStageJob(const MaskStageJob&) = delete;
  MaskStageJob& operator=(const MaskStageJob&) = delete;

  StageRun& run() { return run_; }
  // True when slice k's outputs are recorded with its current inputs (StageRun::up_to_date).
  bool up_to_date(int k) const;
  void skip(int k) { run_.skip(k); }
  // Computes slice k's mask from its registered colour (registered_colour) and CT slice
  // (read_ct_slice), writes mask, overlay and (work.write_ct) the resampled CT, records the slice
  // and returns the mask (CV_8UC1, 0/255). When the config has CT and `ct16` is given, it receives
  // resampled_ct16 of the slice (computed once for the caller). Throws what compute_mask and
  // write_image throw.
  cv::Mat compute(int k, const cv::Mat& rgb, const CtSlice& ct, cv::Mat* ct16 = nullptr);
  // Quality numbers and the report (StageRun::finish).
  StageResult finish();

 private:
  std::string input_fingerprint(int k) const;
  std::vector<std::string> outputs(int k) const;
  const Config& config_;
  const StackInputs& inputs_;
  StageRun run_;
  std::vector<double> coverage_;   // per slice of the range, -1 = not computed
  std::vector<PartCounts> parts_;  // per slice of the range: body parts kept and removed
  std::atomic<long long> compute_ns_{0};
  std::atomic<int> colour_only_{0};
  // Per slice of the range: computed without CT: 1 = outside the CT's z range (slice_z.h),
  // 2 = at a body's tip between two CT slices (CtSlice::body_ends).
  std::vector<char> colour_only_slice_;
  std::mutex gel_mutex_;
  cv::Vec3d gel_sum_{0, 0, 0};
  int gel_count_ = 0;
};

}  // namespace vispack::pipeline

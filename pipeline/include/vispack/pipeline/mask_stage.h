// The mask stage (vispack-mask): the body masks of the whole stack (the algorithm is mask.h).
// Not thread-safe: a stage run sets OpenCV's process-wide thread count for its duration; run one
// stage at a time per process.
#pragma once

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/stage_run.h"

namespace vispack::pipeline {

// vispack-mask: for every output slice writes <work>/mask/mask_NNNN.png, overlay_NNNN.png,
// ct_NNNN.png (when CT is configured) and report.json (per-slice coverage, time, throughput).
// Reads <work>/register/transforms.json and the registered slices (run vispack-register first);
// per-slice work, so --slices shards freely.
StageResult run_mask_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

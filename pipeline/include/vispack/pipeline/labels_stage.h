// The labels stage (vispack-labels): segmentation slices -> label slices on the output grid
// (the matching and resampling are labels.h). Not thread-safe: run one stage at a time per
// process.
#pragma once

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/stage_run.h"

namespace vispack::pipeline {

// The stage: seg slices -> work/labels/labels_NNNN.png. Needs config.seg (throws ConfigError
// "seg: not configured" otherwise). Depends on config sections "seg" and "rgb" and on
// transforms.json (identity transforms when registration has not run and register.enabled is
// false). Throws InputError (unmatched colour in strict mode, seg slice of the wrong size).
StageResult run_labels_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

// The register stage (vispack-register): the transforms of the whole stack, the registered
// colour slices and the QC pictures (the algorithms are register.h). Not thread-safe: a stage
// run sets OpenCV's process-wide thread count for its duration; run one stage at a time per
// process.
#pragma once

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"

namespace vispack::pipeline {

// vispack-register: reads the rgb stack (and the CT if configured), writes
//   <work>/register/pairs/pairs_NNNN.json   per-slice record: pair edges, fiducials, CT anchor
//                                           (the sharded part)
//   <work>/register/pairs/picture_NNNN.png  the slice's overlay picture (≤ 512 px, its
//                                           identity in the record), written as the slice is
//                                           read for its record: the QC overlay after the
//                                           solve warps it instead of the full-size slice, and
//                                           no run keeps its range's pictures in memory (flat
//                                           memory whatever the stack's length)
//   <work>/register/transforms.json         the solved transforms ("frame": "ct" with CT; the
//                                           defined ct_to_rgb; per-slice anchor confidence and
//                                           residual)
//   <work>/register/registered/rgb_NNNN.png the colour slices resampled onto the output grid
//   <work>/register/qc/overlay_NNNN.png     the CT outline over the registered slice (≤ 512 px)
//   <work>/register/qc/transforms.png       dx, dy, rotation over the stack with anchors,
//                                           confidences, jumps and overrides
//   <work>/register/report.json             time, anchor mode, anchors used, jumps, overrides,
//                                           warnings ("absolute drift is not observable")
// The anchor mode is register.anchor ("auto": ct when configured, else fiducials when found,
// else none). Without an absolute anchor the stage warns on stderr and in the report.
// Sharded runs (options.slices = "A:B") compute the records of [A, B) (reading slices down to
// A−4 for the edges into A) and keep each slice's overlay picture with its record (as an
// unsharded run does). The run that
// finds every slice's record present (whichever shard finishes last, or the unsharded run)
// solves and writes transforms.json; a shard writes registered slices and QC overlays of its
// range only when transforms.json covers the whole stack. So a scheduler runs all shards, then
// runs the shards (or one unsharded run) again: the second pass reuses the records and only
// solves and resamples. With options.records_only (--records-only: a cluster's first pass,
// scripts/vispack-slurm with two shards or more) a run stops after its records (and pictures),
// even when they complete the set: every shard of the pass then does the same work, so an array
// of them takes as long as its slowest measure, not that plus one shard's solve and overlays.
// Shards that solve at the same time find the same transforms and leave transforms.json as it
// is (compared in memory).
StageResult run_register_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

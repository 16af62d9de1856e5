// The streaming run (vispack-run's default; docs/ARCHITECTURE.md, 'The streaming run'): mask,
// labels and pack in ONE pass over the stack, after the register stage (which needs the whole stack
// for its global solve) and before the vdb stage (a separate step).
//
// Each stack slice k (of the whole stack, or of a shard: below) is read once (input colour, CT
// slice, segmentation slice); its registered colour and resampled CT are computed once; its mask
// (mask.h) and labels (labels.h) are computed and written as vispack-mask and vispack-labels write
// them (mask PNG, overlay, label PNG; CT only with work.write_ct), recorded in those stages'
// manifests (MaskStageJob, LabelsStageJob), and the slice is converted and handed to the pack
// Writer (PackStream) in z order through a reorder queue. Workers: options.threads
// (resolve_threads) take slices in stack order; at most 2 x threads slices are claimed and not yet
// appended, so memory is bounded by that many slices' images plus the Writer's slab (one brick
// row).
//
// Same results as the staged stages: the packed file is byte-identical to vispack-mask,
// vispack-labels and vispack-pack run one after another, and their manifests record the same
// inputs and outputs, so either kind of run finds the other's work up to date. A slice whose mask
// (or labels) is up to date is not recomputed: its PNG is read back for the pack. When every mask
// and label slice is up to date, the pack is run_pack_stage (up to date itself, or reading the
// work folder). When the pack needs every slice before the first one is packed
// (PackStream::streamable false: pack.crop_margin_px, or segmentation without a palette), the
// pass computes masks and labels only and run_pack_stage then reads them back.
//
// Not thread-safe with other stages in the same process (OpenCV's thread count is set to 1 for
// the pass: the workers are the parallelism).
#pragma once

#include <vector>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"

namespace vispack::pipeline {

// Runs mask, labels (with a seg section) and pack over the whole stack, or over the shard
// options.slices = "A:B", as described above and returns their results in that order;
// options.force recomputes every slice. A shard writes the masks and labels of [A, B) (the
// shard manifests of vispack-mask and vispack-labels --slices A:B) and the pack's slab files of
// the slabs that start in [A, B) (vispack-pack --slices A:B; PackStream): streamed when those
// slabs end inside the range (a cluster's whole-slab shards), else read back from the work folder
// after the pass, so their slices beyond B must be there already. Throws what the stages throw
// (naming the file or slice); on an error the pack output is left as it was and the slices (and
// a shard's slabs) finished so far stay recorded.
std::vector<StageResult> run_stream(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

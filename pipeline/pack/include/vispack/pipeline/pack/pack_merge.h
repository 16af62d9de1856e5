// The merge of a sharded pack (pack.h "Sharding"): the packed file from the shards' slab files.
// Its own header so that the merge (library vispack_pipeline_pack_merge, tool vispack-merge)
// compiles and links without the image code of the whole-stack pack.
#pragma once

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"

namespace vispack::pipeline {

// vispack-pack --merge and vispack-merge: writes config.output from <work>/pack-slabs/ (see
// "Sharding" above). Reads no image (a crop's body bounds come from slab 0's header), so
// vispack-merge links no image library (pack/src/pack_merge.cpp).
// Throws UsageError (options.slices set), InputError (a slab file missing, foreign or out of
// date, naming it and the shard to rerun), FormatError (a corrupt slab file), IoError.
StageResult run_pack_merge(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

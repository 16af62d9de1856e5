// vispack-merge: the packed file from a sharded pack's slab files (pipeline/pack/pack.h
// "Sharding"), the same work as vispack-pack --merge. It links no image library (nothing in a merge
// reads a slice), so it starts in a fraction of vispack-pack's time: the step a cluster runs alone
// between the shards and the OpenVDB export.
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/pack/pack_merge.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-merge", argc, argv,
      "Writes the packed volume (config \"output\") from the slab files that the pack shards "
      "(vispack-pack --slices A:B, or vispack-run --slices A:B) left in WORK/pack-slabs: their "
      "compressed level-0 bricks are copied as they are, the coarser levels are built from their "
      "level-1 slices, and the file is byte-identical to an unsharded pack (format/SPEC.md "
      "\"Partial slab files\"). The same as vispack-pack --merge, without the image libraries' "
      "start-up. Refuses a missing, foreign or out-of-date slab file, naming it and the shard to "
      "rerun.",
      vispack::pipeline::run_pack_merge, /*sharded=*/false);
}

// vispack-register: slice-to-slice drift of the colour stack and the CT -> colour alignment.
#include "vispack/pipeline/register/register_stage.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-register", argc, argv,
      "Registers the colour stack (rigid drift, jumps, black and duplicate slices) and aligns the "
      "CT to it. Writes <work>/register/transforms.json, qc/ overlays and report.json (and the "
      "full-size registered/rgb_NNNN.png with work.write_registered). "
      "Sharded runs (--slices A:B) compute their pair records; the run that completes the set "
      "chains them, and each shard writes its QC overlays (and copies) once transforms.json exists "
      "(run the shards twice). --records-only: a first pass that only measures the records, "
      "whether or not they complete the set (a cluster's measure step: every shard does the same "
      "work).",
      vispack::pipeline::run_register_stage, true, "[--records-only]",
      [](vispack::Args& args, vispack::pipeline::StageOptions& options) {
        options.records_only = args.flag(
            "--records-only", "measure the range's pair records and stop (no solve, no QC)");
      });
}

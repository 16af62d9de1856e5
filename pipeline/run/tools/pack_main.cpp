// vispack-pack: see pipeline/pack/pack.h.
#include <iostream>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_lock.h"
#include "vispack/pipeline/pack/pack.h"

int main(int argc, char** argv) {
  using namespace vispack;
  using namespace vispack::pipeline;
  const std::string program = "vispack-pack";
  return run_main(program, argc, argv, [&](Args& args) {
    args.describe(
        "--config CONFIG [--slices A:B | --merge] [--force] [--quiet] [--threads N]",
        "Builds the packed volume (config \"output\") from the intermediates: rgba = registered "
        "colour + body mask as alpha, ct = HU, labels = IDs, with the label table, slice defects, "
        "registration quality and provenance in the metadata. Sharded (a cluster): each "
        "--slices A:B shard encodes the level-0 brick slabs (pack.brick_edge slices along z) "
        "whose first slice lies in [A, B) into WORK/pack-slabs/slab_NNNN.vpkslab; then one "
        "--merge copies their compressed bricks into the file, computes the coarser levels and "
        "gives a file byte-identical to an unsharded pack (format/SPEC.md \"Partial slab "
        "files\").");
    auto config_path = args.option("--config", "CONFIG", "pipeline config (JSON)");
    StageOptions options;
    options.slices = args.option("--slices", "A:B",
                                 "a shard: encode the slabs starting in stack indices [A, B)", "");
    const bool merge =
        args.flag("--merge", "write the output from every shard's slab files (after the shards)");
    options.force = args.flag("--force", "redo even if up to date");
    options.quiet = args.flag("--quiet", "no progress or summary output");
    auto threads =
        args.option_int("--threads", "N", "threads in all, this one included (default: all cores)");
    args.done();
    if (!config_path) throw UsageError("--config CONFIG is required");
    if (threads) {
      if (*threads < 1 || *threads > 4096) throw UsageError("--threads must be in 1..4096");
      options.threads = int(*threads);
    }
    if (merge && !options.slices.empty())
      throw UsageError("--merge takes no --slices: it builds the whole file from every shard");
    Config config = load_config(*config_path);
    const auto lock = WorkFolderLock::acquire(config.work_dir, options.slices);
    keep_slice_buffers();
    StageResult result = merge ? run_pack_merge(config, options) : run_pack_stage(config, options);
    if (!options.quiet) {
      std::cout << result.stage << ": " << result.processed << " computed, " << result.skipped
                << " up to date in " << result.seconds << " s -> " << result.output << "\n";
    }
    return 0;
  });
}

// vispack-run: every pipeline stage in order, skipping what is up to date (pipeline/run/run.h).
#include <iostream>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/core/work_lock.h"
#include "vispack/pipeline/run/plan.h"
#include "vispack/pipeline/run/run.h"

int main(int argc, char** argv) {
  using namespace vispack;
  return run_main("vispack-run", argc, argv, [](Args& args) {
    args.describe(
        "CONFIG [--from STAGE] [--to STAGE] [--slices A:B] [--force] [--quiet] [--threads N] "
        "[--staged] [--plan]",
        "Runs register -> mask -> labels -> pack -> vdb on the config's slice folders "
        "(labels only with a seg section, vdb only when enabled), skipping slices and "
        "stages whose outputs are up to date with their inputs and config, and prints "
        "where each output is. By default mask, labels and pack run as one streaming "
        "pass after register (each slice read once, its work spread over the threads, "
        "the same files and manifests as the stages run one by one); vdb follows.");
    pipeline::RunOptions options;
    options.from = args.option("--from", "STAGE", "first stage to run", "register");
    options.to =
        args.option("--to", "STAGE", "last stage to run (default: vdb; with --slices: pack)")
            .value_or("");
    options.slices = args.option("--slices", "A:B",
                                 "one shard of stack indices [A, B) for a cluster "
                                 "(scripts/vispack-slurm): every stage runs on the shard, the pack "
                                 "writes the slab files of the slabs that start in it (merge them "
                                 "with vispack-pack --merge; default: the whole stack)")
                         .value_or("");
    options.force = args.flag("--force", "recompute every stage in range");
    options.quiet = args.flag("--quiet", "no progress output");
    options.staged = args.flag("--staged",
                               "run mask, labels and pack one after another, each re-reading "
                               "the work folder (instead of the one streaming pass)");
    auto threads =
        args.option_int("--threads", "N", "threads in all, this one included (default: all cores)");
    const bool plan = args.flag(
        "--plan",
        "the dry run: check the config, read the first and the last slice of every input "
        "folder (and the colour stack's middle one, as register does), print \"slices N\", "
        "\"stages ...\" (the stages the config enables), \"pack_slab_slices E\" (slices per "
        "level-0 slab of the pack; 0 when a colour file is missing inside the stack) and one "
        "\"input ...\" line per folder, and exit: a wrong "
        "raw size, layout or header or a file that is not an image fails here with the run's "
        "error; writes nothing");
    std::string config_path = args.positional("CONFIG", "pipeline config (JSON)");
    args.done();
    if (threads) {
      if (*threads < 1 || *threads > 4096) throw UsageError("--threads must be in 1..4096");
      options.threads = int(*threads);
    }
    pipeline::Config config = pipeline::load_config(config_path);
    if (plan) {
      const pipeline::Plan p = pipeline::plan_run(config);
      for (const auto& w : p.warnings)
        std::cerr << "vispack-run: warning: " << w << "\n";
      std::cout << pipeline::format_plan(p);
      return 0;
    }
    const auto lock = pipeline::WorkFolderLock::acquire(config.work_dir, options.slices);
    pipeline::keep_slice_buffers();
    for (const auto& r : pipeline::run_pipeline(config, options)) {
      std::cout << r.stage << ": " << (r.processed ? "ran" : "up to date") << " (" << r.processed
                << " computed, " << r.skipped << " up to date, " << r.seconds << " s) -> "
                << r.output << "\n";
    }
    return 0;
  });
}

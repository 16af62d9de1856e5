// vispack-run: every stage in order, in-process, skipping what is up to date.
//
// Order: register -> mask -> labels -> pack -> vdb. By default (streaming, stream.h) mask,
// labels and pack run as one pass over the stack when [from, to] holds all three: register
// first (its global solve needs the whole stack), then the one pass, then vdb. With `staged`
// (vispack-run --staged) each stage runs on its own, one after another, re-reading its inputs
// from the work folder. Both give the same files (the packed file byte for byte) and the same
// stage manifests. "labels" is skipped when the config has no
// "seg" section, "vdb" when vdb.enabled is false; "register" with register.enabled = false is
// still called (it writes identity transforms and copies the slices, per register.h).
// Each stage decides per slice (or per output file) what is stale (core/stage_run.h), so a second
// run recomputes nothing, and a changed config section reruns its stage; later stages then see new
// input files and rerun too.
#pragma once

#include <string>
#include <vector>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"

namespace vispack::pipeline {

// "register", "mask", "labels", "pack", "vdb".
const std::vector<std::string>& pipeline_stage_names();

struct RunOptions {
  std::string from;    // first stage to run (empty: "register")
  std::string to;      // last stage to run (empty: "vdb"; with `slices`, "pack" unless from is vdb)
  bool force = false;  // recompute every stage in [from, to]
  bool quiet = false;
  int threads = 0;
  bool staged = false;  // one stage after another instead of the streaming pass
  // "A:B": a shard of stack indices (every stage in range runs with --slices A:B, the streaming
  // pass over [A, B) only; stream.h). A shard's pack writes slab files, not the packed file, so
  // the range may not hold both pack and an enabled vdb (the vdb shards read the merged file:
  // run vispack-pack --merge between them). Empty: the whole stack.
  std::string slices;
};

// Runs the stages [from, to] that the config enables. Throws UsageError for an unknown stage
// name, from after to, or a shard whose range holds pack and vdb; otherwise whatever a stage throws
// (the stage's own errors).
std::vector<StageResult> run_pipeline(const Config& config, const RunOptions& options);

}  // namespace vispack::pipeline

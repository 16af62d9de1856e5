#include "vispack/pipeline/run/run.h"

#include <algorithm>
#include <iostream>

#include "vispack/common/error.h"
#include "vispack/common/test_pause.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/labels/labels_stage.h"
#include "vispack/pipeline/mask/mask_stage.h"
#include "vispack/pipeline/pack/pack.h"
#include "vispack/pipeline/register/register_stage.h"
#include "vispack/pipeline/run/stream.h"
#include "vispack/pipeline/vdb/vdb.h"

namespace vispack::pipeline {

const std::vector<std::string>& pipeline_stage_names() {
  static const std::vector<std::string> names = {"register", "mask", "labels", "pack", "vdb"};
  return names;
}

std::vector<StageResult> run_pipeline(const Config& config, const RunOptions& options) {
  const auto& names = pipeline_stage_names();
  auto position = [&](const std::string& name, int fallback) {
    if (name.empty()) return fallback;
    auto it = std::find(names.begin(), names.end(), name);
    if (it == names.end())
      throw UsageError(
          cat("unknown stage '", name, "' (stages: register, mask, labels, pack, vdb)"));
    return int(it - names.begin());
  };
  const int pack_at = position("pack", 0), vdb_at = position("vdb", 0);
  const int from = position(options.from, 0);
  // A shard stops at pack unless told otherwise (its vdb part needs the merged file).
  const int to = position(options.to, options.slices.empty() || from > pack_at ? vdb_at : pack_at);
  if (from > to) throw UsageError(cat("--from ", options.from, " comes after --to ", options.to));
  StageOptions stage_options;
  stage_options.force = options.force;
  stage_options.quiet = options.quiet;
  stage_options.threads = options.threads;
  stage_options.slices = options.slices;
  const bool vdb_enabled = config.vdb.enabled && !config.vdb_output.empty();
  if (!options.slices.empty() && from <= pack_at && to >= vdb_at && vdb_enabled)
    throw UsageError(
        cat("--slices ", options.slices,
            ": a shard's pack writes slab files and the OpenVDB shards read the merged "
            "file: run up to --to pack, then vispack-merge, then --from vdb"));
  std::vector<StageResult> results;
  // Streaming (stream.h): mask, labels and pack in one pass, when the range holds all three.
  const int mask_at = position("mask", 0);
  const bool stream = !options.staged && from <= mask_at && to >= pack_at;
  for (int i = from; i <= to; ++i) {
    const std::string& name = names[i];
    if (stream && i > mask_at && i <= pack_at) continue;  // done by run_stream at "mask"
    if (stream && i == mask_at) {
      if (test_pause_enabled()) test_pause_point("before:mask");
      for (auto& r : run_stream(config, stage_options))
        results.push_back(r);
      continue;
    }
    if (name == "labels" && !config.seg) continue;
    if (name == "vdb" && (!config.vdb.enabled || config.vdb_output.empty())) continue;
    if (test_pause_enabled()) test_pause_point("before:" + name);
    StageResult r;
    if (name == "register") r = run_register_stage(config, stage_options);
    if (name == "mask") r = run_mask_stage(config, stage_options);
    if (name == "labels") r = run_labels_stage(config, stage_options);
    if (name == "pack") r = run_pack_stage(config, stage_options);
    if (name == "vdb") r = run_vdb_stage(config, stage_options);
    if (r.stage.empty()) r.stage = name;
    results.push_back(r);
  }
  return results;
}

}  // namespace vispack::pipeline

// Test helper: a phantom preset written into a folder, with its loaded config (shared by the
// pipeline tests that score a stage against the phantom's truth).
#pragma once

#include <cstdlib>
#include <filesystem>
#include <string>

#include "test_support.h"
#include "vispack/phantom/phantom.h"
#include "vispack/phantom/score.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/labels/labels_stage.h"
#include "vispack/pipeline/mask/mask_stage.h"
#include "vispack/pipeline/register/register_stage.h"

namespace vispack::test {

// Writes phantom `preset` (seed; slice count, 0 = the preset's own) into `dir` quietly and
// returns the config it wrote (dir/config.json), loaded.
inline pipeline::Config make_phantom_case(const std::filesystem::path& dir,
                                          const std::string& preset, int seed, int slices = 0) {
  phantom::PhantomOptions options;
  options.preset = preset;
  options.seed = seed;
  options.slices = slices;
  options.quiet = true;
  phantom::make_phantom(dir, options);
  return pipeline::load_config(dir / "config.json");
}

// A sample folder ($VISPACK_SAMPLES_DIR or <source>/data/samples, then /<name>), or "" when it
// has not been fetched (scripts/fetch-sample-data.sh <name>).
inline std::string sample_folder(const std::string& name) {
  const char* env = std::getenv("VISPACK_SAMPLES_DIR");
  const std::string sample =
      (env && *env ? std::string(env) : source_dir() + "/data/samples") + "/" + name;
  return std::filesystem::exists(sample + "/.stamp") ? sample : "";
}
inline std::string head_ct_sample() {
  return sample_folder("head-ct");
}

// Stage options for a whole, quiet, unforced run.
inline pipeline::StageOptions quiet_stage_options() {
  pipeline::StageOptions options;
  options.quiet = true;
  return options;
}

// Register, mask and labels on `config` (a phantom case written into `dir`), quietly, scored
// against the phantom's truth.
inline phantom::Score run_stages_and_score(const std::filesystem::path& dir,
                                           const pipeline::Config& config) {
  const pipeline::StageOptions so = quiet_stage_options();
  pipeline::run_register_stage(config, so);
  pipeline::run_mask_stage(config, so);
  pipeline::run_labels_stage(config, so);
  return phantom::score_work((dir / "truth").string(), config.work_dir);
}

}  // namespace vispack::test

// The stage runner every pipeline stage shares: resume (which slices are up to date), shards
// (--slices A:B), progress, the stage report, and the common command line of a stage
// executable. Paths of the work folder are in work_layout.h.
//
// A stage (register, mask, labels, pack, vdb) is a library function
//   StageResult run_<stage>_stage(const Config& config, const StageOptions& options);
// that vispack-run calls in-process and that tools/<stage>_main.cpp wraps with stage_main().
// A typical per-slice stage body:
//
//   StageResult run_mask_stage(const Config& config, const StageOptions& options) {
//     auto slices = stack_slices(config);                       // the rgb stack, sorted
//     StageRun run(config, "mask", int(slices.size()), options, {"mask", "ct", "rgb"},
//                  {transforms_path(config)});                   // stage-wide inputs
//     parallel_for(run.range().size(), run.threads(), [&](std::int64_t i) {
//       int k = run.range().first + int(i);
//       std::string in = Fingerprint().file(registered_rgb_path(config, k)).file(ct_file(k)).str();
//       std::vector<std::string> outs = {run.slice_path("mask", k), run.slice_path("overlay", k)};
//       if (run.up_to_date(k, in, outs)) { run.skip(k); return; }
//       ... compute, write_image(outs[0], ...), write_image(outs[1], ...) ...
//       run.done(k, in, outs, bytes_read);
//     });
//     run.set_quality("mean_coverage", 0.41);
//     return run.finish();                                       // manifest + report.json
//   }
//
// Resume and staleness. Each stage folder holds a manifest (written atomically, flushed every
// few seconds while a stage runs and at finish) recording
//   - the stage hash: config_section_hash(config, sections) combined with the fingerprints of
//     the stage-wide inputs (e.g. work/register/transforms.json) and the vispack version;
//   - per slice: the input fingerprint the stage computed and the fingerprints of the outputs
//     it wrote (size + mtime in nanoseconds).
// A slice is up to date when the manifest's stage hash equals the current one, its input
// fingerprint is unchanged, and every output it recorded still exists with the recorded size
// and mtime. So a changed config section or stage-wide input redoes the whole stage; a changed
// input file redoes that slice; a deleted or overwritten output redoes that slice; an
// interrupted run redoes only what it had not recorded. --force redoes everything.
//
// Shards. `--slices A:B` (half-open, stack indices, parse_slice_range) restricts a run to
// [A, B). A shard writes its own manifest, "manifest-A-B.json", and report, "report-A-B.json",
// so shards on several machines sharing one work folder never write the same file; every
// manifest in the folder is read when deciding what is up to date. An unsharded run writes
// "manifest.json" and "report.json" and, at finish, folds the shard manifests into its own and
// removes them. A stage whose work is not per-slice (register chains transforms over the whole
// stack) may refuse shards with a UsageError.
//
// Thread-safety: StageRun's up_to_date / done / skip / set_quality / add_bytes may be called
// concurrently from parallel_for workers; the constructor and finish() from one thread.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "vispack/common/cli.h"
#include "vispack/common/progress.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/fingerprint.h"

namespace vispack::pipeline {

// Options shared by every stage (the common command line).
struct StageOptions {
  std::string slices;  // "A:B" shard of stack indices; empty = the whole stack
  bool force = false;  // redo every slice of the range even if up to date
  bool quiet = false;  // no progress output
  int threads = 0;     // worker threads; 0 = resolve_threads() (all cores, VISPACK_THREADS)
  // vispack-register --records-only: measure the range's pair records and stop, even when they
  // complete the set (the first pass of a sharded run: register_stage.h). Other stages ignore it.
  bool records_only = false;
};

// What a stage run did, for vispack-run's summary.
struct StageResult {
  std::string stage;
  int processed = 0;  // slices (or units) computed in this run
  int skipped = 0;    // slices found up to date
  double seconds = 0.0;
  std::string output;  // the main output (folder or file), absolute
  std::string report;  // path of the report written
  bool up_to_date() const { return processed == 0; }
};

// ---- StageRun ----

class StageRun {
 public:
  // Creates <work>/<stage>/, resolves the range (options.slices against slice_count; throws
  // UsageError on a bad range), computes the stage hash from `sections` (config sections the
  // stage depends on) and the identities of `stage_inputs` (files), loads the manifests and
  // starts a Progress over the range ("<stage>", "slices").
  StageRun(const Config& config, std::string stage, int slice_count, const StageOptions& options,
           std::vector<std::string> sections, std::vector<std::string> stage_inputs = {});
  ~StageRun();
  StageRun(const StageRun&) = delete;
  StageRun& operator=(const StageRun&) = delete;

  const Config& config() const { return config_; }
  const std::string& stage() const { return stage_; }
  const std::string& dir() const { return dir_; }
  SliceRange range() const { return range_; }
  bool sharded() const { return sharded_; }
  int slice_count() const { return slice_count_; }
  int threads() const { return threads_; }
  const std::string& stage_hash() const { return stage_hash_; }
  const StageOptions& options() const { return options_; }

  // Removes temporaries ("<final>.tmp-*") that a killed run left for `final_path`, an output
  // outside the stage folder (the packed file, the OpenVDB file). Temporaries inside the stage
  // folder are removed by the constructor: all of them for an unsharded run, those of the
  // shard's own slices for a sharded one.
  void remove_stale_temporaries_of(const std::string& final_path) const;

  // <dir>/<prefix>_NNNN.<ext>
  std::string slice_path(const std::string& prefix, int index,
                         const std::string& ext = "png") const;

  // True if slice `index` was recorded with this stage hash and `input_fingerprint`, and every
  // recorded output still has its recorded identity (and `outputs` are exactly those recorded).
  // Always false with --force.
  bool up_to_date(int index, const std::string& input_fingerprint,
                  const std::vector<std::string>& outputs) const;
  // The outputs recorded for slice `index` by an earlier run (empty when none was recorded, or
  // it recorded none): for a unit whose outputs are known only after costly planning (a vdb
  // shard's parts), checked with up_to_date(index, input, recorded_outputs(index)).
  std::vector<std::string> recorded_outputs(int index) const;
  // True if every slice of the range is up to date by the records alone (outputs checked):
  // for stages that do whole-stack work (register) and want to skip it entirely.
  bool all_up_to_date() const;
  // Records slice `index` as computed (outputs already written) and advances the progress.
  // `bytes` (input bytes read) feeds the report's MB/s.
  void done(int index, const std::string& input_fingerprint,
            const std::vector<std::string>& outputs, std::uint64_t bytes = 0);
  // Writes the manifest now with the slices recorded so far (done() writes it at most every
  // 2 s): for a run that stops on an error and wants its finished slices kept for the resume.
  void flush();
  // Advances the progress for a slice found up to date.
  void skip(int index);
  void add_bytes(std::uint64_t bytes);

  // Quality numbers (or any JSON) stored under report["quality"][key].
  void set_quality(const std::string& key, nlohmann::json value);
  // Anything else the stage wants in the report, under report[key].
  void set_report(const std::string& key, nlohmann::json value);

  // Flushes the manifest, writes report.json (or report-A-B.json for a shard) atomically:
  //   { "stage", "vispack_version", "time_utc", "seconds", "slice_range": [A, B],
  //     "slice_count", "processed", "skipped", "slices_per_s", "mb_per_s", "config_hash",
  //     "stage_hash", "quality": {...}, ... }
  // and returns the summary. `output` is the stage's main output (default: dir()).
  StageResult finish(const std::string& output = "");

 private:
  void flush_manifest_locked(bool final);
  const Config& config_;
  std::string stage_, dir_;
  StageOptions options_;
  int slice_count_ = 0;
  SliceRange range_;
  bool sharded_ = false;
  int threads_ = 1;
  std::string config_hash_, stage_hash_, manifest_path_, report_path_;
  mutable std::mutex mutex_;
  void remove_stale_temporaries() const;
  nlohmann::json previous_;  // "index" -> {input, outputs{path: identity}} from all manifests
  nlohmann::json current_;   // entries recorded by this run (plus still-valid previous ones)
  nlohmann::json report_ = nlohmann::json::object();
  std::unique_ptr<Progress> progress_;
  int processed_ = 0, skipped_ = 0;
  std::uint64_t bytes_ = 0;
  double last_flush_ = 0.0;
};

// Keeps full-size slice buffers (2 to 10 MB at 2048x1216, allocated and freed for every slice)
// in the process's heap: with glibc's defaults each freed buffer goes back to the kernel (heap
// trimmed above 128 KB) and the next slice faults its pages in again (17 % of vispack-register's
// samples; vispack-run spent 4.4 s of its 21 s register step in the kernel on 128 slices at
// 2048x1216, 0.4 s with this). Buffers up to 32 MB stay in the heap and up to 64 MB of free heap
// is kept for reuse; larger blocks (a pack slab) are still mapped and unmapped, so the peak
// resident memory does not change. Process-wide (mallopt): call it from an executable's main
// only, before its threads start; stage_main calls it.
void keep_slice_buffers();

// The common shape of a stage executable:
//   vispack-<stage> --config CONFIG [--slices A:B] [--force] [--quiet] [--threads N]
// Parses those, loads the config, runs `body` and prints the result (unless --quiet) as
// "<stage>: N slices computed, M up to date in S s -> OUTPUT". Exit codes as run_main.
// `sharded` false: a whole-stack tool (vispack-merge), without --slices. `extra` declares a
// tool's own options on `args` and sets them in `options` (before args.done()); `extra_usage`
// shows them on the usage line ("[--records-only]").
int stage_main(const std::string& program, int argc, char** argv, const std::string& description,
               const std::function<StageResult(const Config&, const StageOptions&)>& body,
               bool sharded = true, const std::string& extra_usage = "",
               const std::function<void(Args&, StageOptions&)>& extra = {});

}  // namespace vispack::pipeline

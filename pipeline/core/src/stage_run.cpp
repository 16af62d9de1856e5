#include "vispack/pipeline/core/stage_run.h"

#ifdef __GLIBC__
#include <malloc.h>
#endif
#include <cctype>

#include <sys/stat.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <iostream>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"
#include "vispack/common/test_pause.h"
#include "vispack/pipeline/core/version.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/core/work_lock.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

namespace {

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::string utc_now() {
  std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buffer[32];
  std::strftime(buffer, sizeof buffer, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buffer;
}

}  // namespace

namespace {

// The final path a temporary file stands for ("x.png.tmp-123-4" -> "x.png"), or "" if `name` is
// not a temporary (AtomicFile and the vdb writer name temporaries "<final>.tmp-<pid>[-<n>]").
std::string temporary_target(const std::string& name) {
  auto at = name.find(".tmp-");
  return at == std::string::npos ? std::string() : name.substr(0, at);
}

// The stack index in an output name such as "mask_0007.png", or -1.
int index_in_name(const std::string& name) {
  auto dot = name.rfind('.');
  auto underscore = name.rfind('_', dot);
  if (dot == std::string::npos || underscore == std::string::npos || dot <= underscore + 1)
    return -1;
  int index = 0;
  for (std::size_t i = underscore + 1; i < dot; ++i) {
    if (!std::isdigit(static_cast<unsigned char>(name[i]))) return -1;
    if (index > 100000000) return -1;
    index = index * 10 + (name[i] - '0');
  }
  return index;
}

}  // namespace

void StageRun::remove_stale_temporaries() const {
  // A run killed by SIGKILL (or a power cut) leaves its temporaries behind; they never hold a
  // final name, so removing them loses nothing. An unsharded run owns the whole stage folder; a
  // shard removes only the temporaries of its own slices, since other shards may be running.
  std::error_code ec;
  std::vector<fs::path> stale;
  for (auto it = fs::recursive_directory_iterator(dir_, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    std::string target = temporary_target(it->path().filename().string());
    if (target.empty()) continue;
    if (sharded_ && !range_.contains(index_in_name(target))) continue;
    stale.push_back(it->path());
  }
  for (const auto& path : stale)
    fs::remove(path, ec);
}

void StageRun::remove_stale_temporaries_of(const std::string& final_path) const {
  std::error_code ec;
  fs::path target(final_path);
  fs::path folder = target.parent_path().empty() ? fs::path(".") : target.parent_path();
  std::string prefix = target.filename().string() + ".tmp-";
  std::vector<fs::path> stale;
  for (const auto& entry : fs::directory_iterator(folder, ec))
    if (entry.path().filename().string().rfind(prefix, 0) == 0) stale.push_back(entry.path());
  for (const auto& path : stale)
    fs::remove(path, ec);
}

StageRun::StageRun(const Config& config, std::string stage, int slice_count,
                   const StageOptions& options, std::vector<std::string> sections,
                   std::vector<std::string> stage_inputs)
    : config_(config), stage_(std::move(stage)), options_(options), slice_count_(slice_count) {
  dir_ = stage_dir(config_, stage_);
  make_directories(dir_);
  if (options_.slices.empty()) {
    range_ = SliceRange{0, slice_count_};
  } else {
    range_ = parse_slice_range(options_.slices, slice_count_);
    sharded_ = !(range_.first == 0 && range_.last == slice_count_);
  }
  threads_ = resolve_threads(options_.threads);
  config_hash_ = config_section_hash(config_, sections);
  Fingerprint fp;
  fp.text(stage_).text(version_string()).text(config_hash_);
  // By their bytes: small files (transforms.json, a palette, an id map, overrides), and
  // transforms.json is rewritten with the same bytes by every shard that solves (fingerprint.h).
  for (const auto& input : stage_inputs)
    fp.content(input);
  stage_hash_ = fp.str();
  if (sharded_) {
    manifest_path_ = cat(dir_, "/manifest-", range_.first, "-", range_.last, ".json");
    report_path_ = cat(dir_, "/report-", range_.first, "-", range_.last, ".json");
  } else {
    manifest_path_ = dir_ + "/manifest.json";
    report_path_ = dir_ + "/report.json";
  }
  remove_stale_temporaries();
  previous_ = nlohmann::json::object();
  if (!options_.force) {
    std::error_code ec;
    std::vector<std::string> manifests;
    for (const auto& entry : fs::directory_iterator(dir_, ec)) {
      std::string name = entry.path().filename().string();
      if (name.rfind("manifest", 0) == 0 && name.size() > 5 &&
          name.substr(name.size() - 5) == ".json")
        manifests.push_back(entry.path().string());
    }
    std::sort(manifests.begin(), manifests.end());
    for (const auto& path : manifests) {
      try {
        auto m = nlohmann::json::parse(read_file(path, std::size_t(1) << 30));
        if (m.value("stage_hash", "") != stage_hash_) continue;
        for (auto& [key, value] : m["slices"].items())
          previous_[key] = value;
      } catch (const std::exception&) {
        // An unreadable or stale manifest only means that its slices are recomputed.
      }
    }
  }
  current_ = previous_;
  last_flush_ = now_seconds();
  progress_ = std::make_unique<Progress>(stage_, range_.size(), "slices", options_.quiet);
}

StageRun::~StageRun() = default;

std::string StageRun::slice_path(const std::string& prefix, int index,
                                 const std::string& ext) const {
  return slice_output_path(config_, stage_, prefix, index, ext);
}

bool StageRun::up_to_date(int index, const std::string& input_fingerprint,
                          const std::vector<std::string>& outputs) const {
  if (options_.force) return false;
  nlohmann::json entry;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    auto it = previous_.find(std::to_string(index));
    if (it == previous_.end()) return false;
    entry = *it;
  }
  if (!entry.is_object() || entry.value("input", "") != input_fingerprint) return false;
  const auto& recorded = entry["outputs"];
  if (!recorded.is_object() || recorded.size() != outputs.size()) return false;
  for (const auto& out : outputs) {
    auto it = recorded.find(out);
    if (it == recorded.end() || !it->is_string()) return false;
    std::string id = file_identity(out);
    if (id.empty() || id != it->get<std::string>()) return false;
  }
  return true;
}

std::vector<std::string> StageRun::recorded_outputs(int index) const {
  std::vector<std::string> outputs;
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = previous_.find(std::to_string(index));
  if (it == previous_.end() || !it->is_object() || !it->contains("outputs") ||
      !it->at("outputs").is_object())
    return outputs;
  for (auto& [path, id] : it->at("outputs").items())
    outputs.push_back(path);
  return outputs;
}

bool StageRun::all_up_to_date() const {
  if (options_.force) return false;
  for (int k = range_.first; k < range_.last; ++k) {
    nlohmann::json entry;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      auto it = previous_.find(std::to_string(k));
      if (it == previous_.end()) return false;
      entry = *it;
    }
    if (!entry.is_object() || !entry["outputs"].is_object()) return false;
    for (auto& [path, id] : entry["outputs"].items()) {
      if (!id.is_string() || file_identity(path) != id.get<std::string>()) return false;
    }
  }
  return true;
}

void StageRun::done(int index, const std::string& input_fingerprint,
                    const std::vector<std::string>& outputs, std::uint64_t bytes) {
  nlohmann::json entry = {{"input", input_fingerprint}, {"outputs", nlohmann::json::object()}};
  for (const auto& out : outputs)
    entry["outputs"][out] = file_identity(out);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    current_[std::to_string(index)] = std::move(entry);
    ++processed_;
    bytes_ += bytes;
    if (now_seconds() - last_flush_ > 2.0) flush_manifest_locked(false);
  }
  progress_->advance();
  if (test_pause_enabled()) test_pause_point(cat("done:", stage_, ":", index));
}

void StageRun::flush() {
  std::lock_guard<std::mutex> lock(mutex_);
  flush_manifest_locked(false);
}

void StageRun::skip(int index) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    ++skipped_;
  }
  progress_->advance();
}

void StageRun::add_bytes(std::uint64_t bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  bytes_ += bytes;
}

void StageRun::set_quality(const std::string& key, nlohmann::json value) {
  std::lock_guard<std::mutex> lock(mutex_);
  report_["quality"][key] = std::move(value);
}

void StageRun::set_report(const std::string& key, nlohmann::json value) {
  std::lock_guard<std::mutex> lock(mutex_);
  report_[key] = std::move(value);
}

void StageRun::flush_manifest_locked(bool final) {
  nlohmann::json slices = nlohmann::json::object();
  for (auto& [key, value] : current_.items()) {
    int k = std::atoi(key.c_str());
    // A shard records only its own slices so that shards never contradict each other.
    if (sharded_ && !range_.contains(k)) continue;
    if (k < 0 || k >= slice_count_) continue;
    slices[key] = value;
  }
  nlohmann::json manifest = {{"stage", stage_},
                             {"stage_hash", stage_hash_},
                             {"config_hash", config_hash_},
                             {"slice_range", {range_.first, range_.last}},
                             {"slices", std::move(slices)}};
  write_file_atomic(manifest_path_, manifest.dump(1) + "\n");
  last_flush_ = now_seconds();
  if (final && !sharded_) {
    // The full manifest now holds every shard's records: remove the shard manifests.
    std::error_code ec;
    for (const auto& entry : fs::directory_iterator(dir_, ec)) {
      std::string name = entry.path().filename().string();
      if (name.rfind("manifest-", 0) == 0) fs::remove(entry.path(), ec);
    }
  }
}

StageResult StageRun::finish(const std::string& output) {
  progress_->finish();
  double seconds = progress_->elapsed_seconds();
  std::lock_guard<std::mutex> lock(mutex_);
  flush_manifest_locked(true);
  report_["stage"] = stage_;
  report_["vispack_version"] = version_string();
  report_["time_utc"] = utc_now();
  report_["seconds"] = seconds;
  report_["slice_range"] = {range_.first, range_.last};
  report_["slice_count"] = slice_count_;
  report_["processed"] = processed_;
  report_["skipped"] = skipped_;
  report_["slices_per_s"] = seconds > 0 ? processed_ / seconds : 0.0;
  report_["mb_per_s"] = seconds > 0 ? double(bytes_) / 1e6 / seconds : 0.0;
  report_["config_hash"] = config_hash_;
  report_["stage_hash"] = stage_hash_;
  if (!report_.contains("quality")) report_["quality"] = nlohmann::json::object();
  // A run that found everything up to date keeps the report of the run that computed it (its
  // quality numbers still describe the outputs), unless that report is from another config.
  bool keep = false;
  if (processed_ == 0) {
    try {
      auto old = nlohmann::json::parse(read_file(report_path_, std::size_t(64) << 20));
      keep = old.value("stage_hash", "") == stage_hash_;
    } catch (const std::exception&) {
      keep = false;
    }
  }
  if (!keep) write_file_atomic(report_path_, report_.dump(2) + "\n");
  StageResult result;
  result.stage = stage_;
  result.processed = processed_;
  result.skipped = skipped_;
  result.seconds = seconds;
  result.output = output.empty() ? dir_ : output;
  result.report = report_path_;
  return result;
}

// ---- stage_main ----

void keep_slice_buffers() {
#ifdef __GLIBC__
  mallopt(M_MMAP_THRESHOLD, 32 << 20);
  mallopt(M_TRIM_THRESHOLD, 64 << 20);
#endif
}

int stage_main(const std::string& program, int argc, char** argv, const std::string& description,
               const std::function<StageResult(const Config&, const StageOptions&)>& body,
               bool sharded, const std::string& extra_usage,
               const std::function<void(Args&, StageOptions&)>& extra) {
  return run_main(program, argc, argv, [&](Args& args) {
    args.describe(
        cat("--config CONFIG ", sharded ? "[--slices A:B] " : "",
            "[--force] [--quiet] [--threads N]", extra_usage.empty() ? "" : " ", extra_usage),
        description);
    auto config_path = args.option("--config", "CONFIG", "pipeline config (JSON)");
    StageOptions options;
    if (sharded)
      options.slices =
          args.option("--slices", "A:B", "process stack indices [A, B) only (a shard)", "");
    options.force = args.flag(
        "--force", sharded ? "redo every slice even if up to date" : "redo even if up to date");
    options.quiet = args.flag("--quiet", "no progress or summary output");
    auto threads =
        args.option_int("--threads", "N", "threads in all, this one included (default: all cores)");
    if (extra) extra(args, options);
    args.done();
    if (!config_path) throw UsageError("--config CONFIG is required");
    if (threads) {
      if (*threads < 1 || *threads > 4096) throw UsageError("--threads must be in 1..4096");
      options.threads = int(*threads);
    }
    Config config = load_config(*config_path);
    const auto lock = WorkFolderLock::acquire(config.work_dir, options.slices);
    keep_slice_buffers();
    StageResult result = body(config, options);
    if (!options.quiet) {
      std::cout << result.stage << ": " << result.processed << " computed, " << result.skipped
                << " up to date in " << result.seconds << " s -> " << result.output << "\n";
    }
    return 0;
  });
}

}  // namespace vispack::pipeline

#include "vispack/pipeline/stage.h"
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
#include "vispack/pipeline/version.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

namespace {

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::string padded(int index) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%04d", index);
  return buffer;
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

// ---- fingerprints and paths ----

std::string file_identity(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return "";
  long long ns = (long long)st.st_mtim.tv_sec * 1000000000LL + st.st_mtim.tv_nsec;
  return cat((long long)st.st_size, ":", ns);
}

Fingerprint& Fingerprint::file(const std::string& path) {
  std::string id = file_identity(path);
  data_ += cat("F", path, "\n", id.empty() ? "missing" : id, "\n");
  return *this;
}

Fingerprint& Fingerprint::text(const std::string& value) {
  data_ += cat("T", value.size(), ":", value, "\n");
  return *this;
}

Fingerprint& Fingerprint::number(double value) {
  char buffer[64];
  std::snprintf(buffer, sizeof buffer, "%.17g", value);
  data_ += cat("N", buffer, "\n");
  return *this;
}

std::string Fingerprint::str() const {
  return hex64(xxh64(data_.data(), data_.size()));
}

std::string stage_dir(const Config& config, const std::string& stage) {
  return config.work_dir + "/" + stage;
}

std::string slice_output_path(const Config& config, const std::string& stage,
                              const std::string& prefix, int index, const std::string& ext) {
  return stage_dir(config, stage) + "/" + prefix + "_" + padded(index) + "." + ext;
}

std::string transforms_path(const Config& config) {
  return stage_dir(config, "register") + "/transforms.json";
}

std::string registered_rgb_path(const Config& config, int index) {
  return stage_dir(config, "register") + "/registered/rgb_" + padded(index) + ".png";
}

std::string mask_path(const Config& config, int index) {
  return slice_output_path(config, "mask", "mask", index);
}

std::string mask_ct_path(const Config& config, int index) {
  return slice_output_path(config, "mask", "ct", index);
}

std::string labels_path(const Config& config, int index) {
  return slice_output_path(config, "labels", "labels", index);
}

std::vector<SliceFile> stack_slices(const Config& config) {
  std::vector<SliceFile> files = list_slices(config.rgb);
  if (config.ct) {
    // CT slice k + slice_offset lies on colour slice k: matched by position, so a CT slice
    // missing inside the CT stack would shift every later one (issue 7). The step is the
    // smallest difference between consecutive CT numbers (1 for ct_0000, ct_0001, ...).
    const std::vector<SliceFile> ct = list_slices(*config.ct);
    int step = 0;
    for (std::size_t i = 1; i < ct.size(); ++i) {
      const int d = ct[i].number - ct[i - 1].number;
      if (step == 0 || d < step) step = d;
    }
    for (std::size_t i = 1; i < ct.size(); ++i) {
      if (ct[i].number - ct[i - 1].number > step) {
        throw InputError(cat(config.ct->dir, ": CT slice ", ct[i - 1].number + step,
                             " is missing (", fs::path(ct[i - 1].path).filename().string(),
                             " is followed by ", fs::path(ct[i].path).filename().string(),
                             "); CT slices are matched to colour slices by position"));
      }
    }
  }
  return files;
}

// ---- transforms.json ----

namespace {

template <class T>
T get_key(const nlohmann::json& object, const char* key, const std::string& where, T fallback,
          bool required) {
  auto it = object.find(key);
  if (it == object.end() || it->is_null()) {
    if (required) throw FormatError(cat(where, ": missing key '", key, "'"));
    return fallback;
  }
  try {
    return it->get<T>();
  } catch (const nlohmann::json::exception&) {
    throw FormatError(cat(where, ": key '", key, "' has the wrong type (", it->dump(), ")"));
  }
}

}  // namespace

StackTransforms read_transforms(const std::string& path) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(read_file(path, std::size_t(1) << 30));
  } catch (const nlohmann::json::parse_error& e) {
    throw FormatError(cat(path, ": not valid JSON: ", e.what()));
  }
  if (!j.is_object()) throw FormatError(cat(path, ": not a JSON object"));
  StackTransforms t;
  t.width = get_key<int>(j, "width", path, 0, true);
  t.height = get_key<int>(j, "height", path, 0, true);
  if (t.width <= 0 || t.height <= 0) throw FormatError(cat(path, ": width/height must be > 0"));
  if (j.contains("center_px")) {
    t.center_px = get_key<std::array<double, 2>>(j, "center_px", path, {}, true);
  } else {
    t.center_px = {(t.width - 1) / 2.0, (t.height - 1) / 2.0};
  }
  t.reference_slice = get_key<int>(j, "reference_slice", path, 0, false);
  auto slices = j.find("slices");
  if (slices == j.end() || !slices->is_array())
    throw FormatError(cat(path, ": missing array 'slices'"));
  for (std::size_t i = 0; i < slices->size(); ++i) {
    const auto& s = (*slices)[i];
    std::string where = cat(path, ": slices[", i, "]");
    if (!s.is_object()) throw FormatError(cat(where, ": not an object"));
    SliceTransform st;
    st.index = get_key<int>(s, "index", where, int(i), false);
    if (st.index != int(i)) throw FormatError(cat(where, ": index ", st.index, " out of order"));
    st.number = get_key<int>(s, "number", where, int(i), false);
    st.file = get_key<std::string>(s, "file", where, "", false);
    st.dx_px = get_key<double>(s, "dx_px", where, 0.0, true);
    st.dy_px = get_key<double>(s, "dy_px", where, 0.0, true);
    st.rotation_deg = get_key<double>(s, "rotation_deg", where, 0.0, true);
    st.jump = get_key<bool>(s, "jump", where, false, false);
    st.black = get_key<bool>(s, "black", where, false, false);
    if (s.contains("duplicate_of") && !s["duplicate_of"].is_null())
      st.duplicate_of = get_key<int>(s, "duplicate_of", where, 0, true);
    st.quality = get_key<double>(s, "quality", where, 1.0, false);
    if (!std::isfinite(st.dx_px) || !std::isfinite(st.dy_px) || !std::isfinite(st.rotation_deg))
      throw FormatError(cat(where, ": transform is not finite"));
    t.slices.push_back(st);
  }
  if (j.contains("ct_to_rgb") && !j["ct_to_rgb"].is_null()) {
    const auto& c = j["ct_to_rgb"];
    std::string where = cat(path, ": ct_to_rgb");
    if (!c.is_object()) throw FormatError(cat(where, ": not an object"));
    CtToRgb ct;
    ct.scale = get_key<double>(c, "scale", where, 1.0, true);
    ct.rotation_deg = get_key<double>(c, "rotation_deg", where, 0.0, false);
    ct.dx_px = get_key<double>(c, "dx_px", where, 0.0, false);
    ct.dy_px = get_key<double>(c, "dy_px", where, 0.0, false);
    if (!(ct.scale > 0) || !std::isfinite(ct.scale))
      throw FormatError(cat(where, ": scale must be > 0"));
    t.ct_to_rgb = ct;
  }
  for (auto& [key, value] : j.items()) {
    if (key != "width" && key != "height" && key != "center_px" && key != "reference_slice" &&
        key != "slices" && key != "ct_to_rgb")
      t.extra[key] = value;
  }
  return t;
}

void write_transforms(const std::string& path, const StackTransforms& t) {
  nlohmann::json j = t.extra.is_object() ? t.extra : nlohmann::json::object();
  j["width"] = t.width;
  j["height"] = t.height;
  j["center_px"] = t.center_px;
  j["reference_slice"] = t.reference_slice;
  nlohmann::json slices = nlohmann::json::array();
  for (const auto& s : t.slices) {
    slices.push_back(
        {{"index", s.index},
         {"number", s.number},
         {"file", s.file},
         {"dx_px", s.dx_px},
         {"dy_px", s.dy_px},
         {"rotation_deg", s.rotation_deg},
         {"jump", s.jump},
         {"black", s.black},
         {"duplicate_of", s.duplicate_of ? nlohmann::json(*s.duplicate_of) : nlohmann::json()},
         {"quality", s.quality}});
  }
  j["slices"] = std::move(slices);
  if (t.ct_to_rgb) {
    j["ct_to_rgb"] = {{"scale", t.ct_to_rgb->scale},
                      {"rotation_deg", t.ct_to_rgb->rotation_deg},
                      {"dx_px", t.ct_to_rgb->dx_px},
                      {"dy_px", t.ct_to_rgb->dy_px}};
  }
  make_directories(fs::path(path).parent_path().string());
  write_file_atomic(path, j.dump(2) + "\n");
}

cv::Matx23d output_to_observed(const SliceTransform& t, const std::array<double, 2>& c) {
  double th = t.rotation_deg * M_PI / 180.0;
  double cs = std::cos(th), sn = std::sin(th);
  // p = c + R (q - c) + d = R q + (c - R c + d)
  double tx = c[0] - (cs * c[0] - sn * c[1]) + t.dx_px;
  double ty = c[1] - (sn * c[0] + cs * c[1]) + t.dy_px;
  return cv::Matx23d(cs, -sn, tx, sn, cs, ty);
}

cv::Matx23d output_to_ct(const CtToRgb& t, const std::array<double, 2>& c,
                         const std::array<double, 2>& cc) {
  // q = c + s R (u - cc) + d  =>  u = cc + R^T (q - c - d) / s
  double th = t.rotation_deg * M_PI / 180.0;
  double cs = std::cos(th), sn = std::sin(th);
  double inv = 1.0 / t.scale;
  // R^T = [[cs, sn], [-sn, cs]]
  double a = cs * inv, b = sn * inv, d = -sn * inv, e = cs * inv;
  double ox = c[0] + t.dx_px, oy = c[1] + t.dy_px;
  double tx = cc[0] - (a * ox + b * oy);
  double ty = cc[1] - (d * ox + e * oy);
  return cv::Matx23d(a, b, tx, d, e, ty);
}

// ---- StageRun ----

StackTransforms read_stack_transforms(const Config& config, int slice_count) {
  const std::string path = transforms_path(config);
  if (!fs::exists(path)) throw InputError(cat(path, ": missing; run vispack-register first"));
  StackTransforms transforms = read_transforms(path);
  if (int(transforms.slices.size()) != slice_count) {
    throw InputError(cat(path, ": has ", transforms.slices.size(), " slices but the stack has ",
                         slice_count, "; rerun vispack-register"));
  }
  return transforms;
}

Fingerprint intermediates_fingerprint(const Config& config, int slice_count) {
  Fingerprint fp;
  fp.file(transforms_path(config));
  for (int k = 0; k < slice_count; ++k) {
    fp.file(registered_rgb_path(config, k)).file(mask_path(config, k));
    if (config.ct) fp.file(mask_ct_path(config, k));
    if (config.seg) fp.file(labels_path(config, k));
  }
  return fp;
}

void require_whole_stack(const StageOptions& options, int slice_count, const std::string& program) {
  if (options.slices.empty()) return;
  SliceRange range = parse_slice_range(options.slices, slice_count);
  if (range.first != 0 || range.last != slice_count) {
    throw UsageError(cat(program,
                         " does not shard: its output is one file written as one stream; "
                         "run it without --slices"));
  }
}

ScopedOpenCvThreads::ScopedOpenCvThreads(int threads) : previous_(cv::getNumThreads()) {
  cv::setNumThreads(threads);
}
ScopedOpenCvThreads::~ScopedOpenCvThreads() {
  cv::setNumThreads(previous_);
}

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
  for (const auto& input : stage_inputs)
    fp.file(input);
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
  return dir_ + "/" + prefix + "_" + padded(index) + "." + ext;
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

int stage_main(const std::string& program, int argc, char** argv, const std::string& description,
               const std::function<StageResult(const Config&, const StageOptions&)>& body) {
  return run_main(program, argc, argv, [&](Args& args) {
    args.describe("--config CONFIG [--slices A:B] [--force] [--quiet] [--threads N]", description);
    auto config_path = args.option("--config", "CONFIG", "pipeline config (JSON)");
    StageOptions options;
    options.slices =
        args.option("--slices", "A:B", "process stack indices [A, B) only (a shard)", "");
    options.force = args.flag("--force", "redo every slice even if up to date");
    options.quiet = args.flag("--quiet", "no progress or summary output");
    auto threads = args.option_int("--threads", "N", "worker threads (default: all cores)");
    args.done();
    if (!config_path) throw UsageError("--config CONFIG is required");
    if (threads) {
      if (*threads < 1 || *threads > 4096) throw UsageError("--threads must be in 1..4096");
      options.threads = int(*threads);
    }
    Config config = load_config(*config_path);
    StageResult result = body(config, options);
    if (!options.quiet) {
      std::cout << result.stage << ": " << result.processed << " computed, " << result.skipped
                << " up to date in " << result.seconds << " s -> " << result.output << "\n";
    }
    return 0;
  });
}

}  // namespace vispack::pipeline

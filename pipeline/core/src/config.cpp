// load_config: every key checked, defaults filled, paths resolved (README.md "The config").
#include "vispack/pipeline/core/config.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <limits>
#include <set>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/pipeline/core/slice_list.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

std::string type_name(const json& v) {
  if (v.is_null()) return "null";
  if (v.is_boolean()) return "a boolean";
  if (v.is_number_integer() || v.is_number_unsigned()) return "an integer";
  if (v.is_number()) return "a number";
  if (v.is_string()) return "a string";
  if (v.is_array()) return "an array";
  return "an object";
}

// The errors found in one config file, in the order found. A "missing (required)" error for a key
// that an unknown key's did-you-mean already names is not listed twice.
class ErrorLog {
 public:
  explicit ErrorLog(const std::string& file) : file_(file) {}
  void add_line(const std::string& line) { lines_.push_back(line); }
  void add(const std::string& key_path, const std::string& message) {
    add_line(cat(file_, ": ", key_path, ": ", message));
  }
  std::size_t count() const { return lines_.size() + quiet_; }
  void count_quietly() { ++quiet_; }
  void suggested(const std::string& key_path) { suggested_.insert(key_path); }
  bool was_suggested(const std::string& key_path) const { return suggested_.count(key_path) > 0; }
  void unknown(const std::string& key_path) { unknown_.insert(key_path); }
  bool known_unknown(const std::string& key_path) const { return unknown_.count(key_path) > 0; }

  // Throws one ConfigError listing every error (at most kMaxConfigErrors lines and a count of the
  // rest); does nothing when there is none.
  void throw_if_any() const {
    if (count() == 0) return;
    std::string text;
    const std::size_t shown = std::min(lines_.size(), kMaxConfigErrors);
    for (std::size_t i = 0; i < shown; ++i)
      text += (i ? "\n" : "") + lines_[i];
    if (lines_.size() > shown)
      text += cat("\n", file_, ": ", lines_.size() - shown, " more error",
                  lines_.size() - shown == 1 ? "" : "s", " not shown (the first ", shown,
                  " are above)");
    throw ConfigError(text);
  }

 private:
  const std::string& file_;
  std::vector<std::string> lines_;
  std::size_t quiet_ = 0;
  std::set<std::string> suggested_, unknown_;
};

// A required key that is absent but already named by an unknown key's did-you-mean: counted, not
// listed again.
struct AlreadyReported {};

// Walks one JSON object, checking each key it is asked for and, at the end, that no other key
// is present (keys starting with '_' are comments and ignored). A key at fault is logged and
// stands in with its default (or a placeholder when it has none), so that every key of the file
// is checked in one run; the checks that need several keys run only when those keys were sound.
class Section {
 public:
  Section(const json& object, std::string path, ErrorLog& log, const std::string& file)
      : object_(object), path_(std::move(path)), file_(file), log_(log) {
    if (!object_.is_object())
      log_.add(path_.empty() ? "(top level)" : path_,
               cat("must be an object, got ", type_name(object_)));
  }

  std::string key_path(const std::string& key) const {
    return path_.empty() ? key : path_ + "." + key;
  }

  [[noreturn]] void fail_at(const std::string& key, const std::string& message) const {
    throw ConfigError(cat(file_, ": ", key, ": ", message));
  }
  [[noreturn]] void fail(const std::string& key, const std::string& message) const {
    fail_at(key_path(key), message);
  }
  // Logs an error and goes on.
  void report(const std::string& key, const std::string& message) const {
    log_.add(key_path(key), message);
  }
  // Logs a required key's absence unless an unknown key's did-you-mean already named it.
  void report_missing(const std::string& key, const std::string& message) const {
    if (log_.was_suggested(key_path(key)))
      log_.count_quietly();
    else
      report(key, message);
  }
  // Errors logged so far in the whole file (compare two counts to see whether keys were sound).
  std::size_t errors() const { return log_.count(); }

  const json* find(const std::string& key) {
    seen_.insert(key);
    if (!object_.is_object()) return nullptr;
    auto it = object_.find(key);
    if (it == object_.end()) return nullptr;
    return &*it;
  }
  bool has(const std::string& key) const { return object_.is_object() && object_.contains(key); }

  std::string string(const std::string& key, std::optional<std::string> fallback) {
    return guarded(fallback.value_or(""), [&] {
      const json* v = find(key);
      if (!v) {
        if (!fallback) missing(key);
        return *fallback;
      }
      if (!v->is_string()) fail(key, cat("must be a string, got ", type_name(*v)));
      return v->get<std::string>();
    });
  }
  std::string choice(const std::string& key, const std::vector<std::string>& allowed,
                     const std::string& fallback) {
    std::string value = string(key, fallback);
    return guarded(fallback, [&] {
      for (const auto& a : allowed)
        if (a == value) return value;
      std::string list;
      for (const auto& a : allowed)
        list += (list.empty() ? "\"" : ", \"") + a + "\"";
      fail(key, cat("\"", value, "\" is not one of ", list));
    });
  }
  bool boolean(const std::string& key, bool fallback) {
    return guarded(fallback, [&] {
      const json* v = find(key);
      if (!v) return fallback;
      if (!v->is_boolean()) fail(key, cat("must be true or false, got ", type_name(*v)));
      return v->get<bool>();
    });
  }
  double number(const std::string& key, std::optional<double> fallback, double lo, double hi,
                bool exclusive_lo = false) {
    return guarded(fallback.value_or(placeholder(lo, hi)), [&] {
      const json* v = find(key);
      if (!v) {
        if (!fallback) missing(key);
        return *fallback;
      }
      if (!v->is_number()) fail(key, cat("must be a number, got ", type_name(*v)));
      double x = v->get<double>();
      check_range(key_path(key), x, lo, hi, exclusive_lo);
      return x;
    });
  }
  long long integer(const std::string& key, std::optional<long long> fallback, long long lo,
                    long long hi) {
    return guarded(fallback.value_or(lo), [&] {
      const json* v = find(key);
      if (!v) {
        if (!fallback) missing(key);
        return *fallback;
      }
      if (!v->is_number_integer() && !v->is_number_unsigned())
        fail(key, cat("must be an integer, got ", type_name(*v)));
      long long x = v->is_number_unsigned()
                        ? (long long)std::min<std::uint64_t>(v->get<std::uint64_t>(), 1ULL << 62)
                        : v->get<long long>();
      if (x < lo || x > hi) fail(key, cat(x, " is out of range [", lo, ", ", hi, "]"));
      return x;
    });
  }
  template <std::size_t N>
  std::array<double, N> numbers(const std::string& key,
                                std::optional<std::array<double, N>> fallback, double lo, double hi,
                                bool exclusive_lo) {
    std::array<double, N> stand_in{};
    stand_in.fill(placeholder(lo, hi));
    return guarded(fallback.value_or(stand_in), [&] {
      const json* v = find(key);
      if (!v) {
        if (!fallback) missing(key);
        return *fallback;
      }
      if (!v->is_array() || v->size() != N) fail(key, cat("must be an array of ", N, " numbers"));
      std::array<double, N> out{};
      for (std::size_t i = 0; i < N; ++i) {
        std::string element = cat(key_path(key), "[", i, "]");
        if (!(*v)[i].is_number())
          fail_at(element, cat("must be a number, got ", type_name((*v)[i])));
        out[i] = (*v)[i].get<double>();
        check_range(element, out[i], lo, hi, exclusive_lo);
      }
      return out;
    });
  }
  Section child(const std::string& key) {
    const json* v = find(key);
    static const json empty = json::object();
    return Section(v ? *v : empty, key_path(key), log_, file_);
  }

  // Unknown keys are errors (check_unknown_keys has named most, with a did-you-mean); call once
  // every known key was asked for.
  void finish() const {
    if (!object_.is_object()) return;
    for (auto it = object_.begin(); it != object_.end(); ++it) {
      const std::string& key = it.key();
      if (!key.empty() && key[0] == '_') continue;
      if (!seen_.count(key) && !log_.known_unknown(key_path(key))) report(key, "unknown key");
    }
  }

  const std::string& file() const { return file_; }

 private:
  // Runs one key's check; an error is logged and `stand_in` returned in place of the value.
  template <class T, class Body>
  T guarded(T stand_in, Body body) {
    try {
      return body();
    } catch (const AlreadyReported&) {
      log_.count_quietly();
    } catch (const ConfigError& e) {
      log_.add_line(e.what());
    }
    return stand_in;
  }
  [[noreturn]] void missing(const std::string& key) const {
    if (log_.was_suggested(key_path(key))) throw AlreadyReported{};
    fail(key, "missing (required)");
  }
  static double placeholder(double lo, double hi) { return std::clamp(1.0, lo, hi); }
  void check_range(const std::string& where, double x, double lo, double hi,
                   bool exclusive_lo) const {
    if (!std::isfinite(x) || x < lo || x > hi || (exclusive_lo && x == lo))
      fail_at(where, cat(x, " is out of range ", exclusive_lo ? "(" : "[", lo, ", ", hi, "]"));
  }
  const json& object_;
  std::string path_;
  const std::string& file_;
  ErrorLog& log_;
  std::set<std::string> seen_;
};

std::string resolve(const std::string& base, const std::string& path) {
  fs::path p(path);
  if (p.is_relative()) p = fs::path(base) / p;
  return p.lexically_normal().string();
}

RawLayout parse_raw(Section s, int default_channels) {
  RawLayout raw;
  raw.width = int(s.integer("width", std::nullopt, 1, 65536));
  raw.height = int(s.integer("height", std::nullopt, 1, 65536));
  raw.channels = int(s.integer("channels", default_channels, 1, 3));
  if (raw.channels == 2) s.report("channels", "must be 1 or 3");
  raw.planar = s.choice("layout", {"planar", "interleaved"}, "interleaved") == "planar";
  raw.bits = int(s.integer("bits", 8, 8, 16));
  if (raw.bits != 8 && raw.bits != 16) s.report("bits", "must be 8 or 16");
  // The header first: a GE Genesis image (the NLM male's CT .fre) stores big-endian samples.
  raw.genesis = s.choice("header", {"none", "genesis"}, "none") == "genesis";
  raw.big_endian = s.choice("endian", {"little", "big"}, raw.genesis ? "big" : "little") == "big";
  raw.header_bytes = std::uint64_t(s.integer("header_bytes", 0, 0, 1LL << 40));
  if (raw.genesis && raw.header_bytes != 0)
    s.report("header_bytes",
             "not used with header \"genesis\" (each file's own header gives the pixel offset); "
             "remove it");
  if (raw.genesis && raw.channels != 1)
    s.report("channels", "must be 1 with header \"genesis\" (a GE Genesis image is grey)");
  s.finish();
  return raw;
}

// dir, pattern and raw of a slice folder; the folder must exist and the pattern match a file
// (checked once the keys themselves are sound).
void parse_source(Section& s, SliceSource& source, const std::string& base,
                  const std::string& default_pattern, int default_channels) {
  const std::size_t errors_before = s.errors();
  std::string dir = s.string("dir", std::nullopt);
  source.dir = resolve(base, dir);
  source.pattern = s.string("pattern", default_pattern);
  if (source.pattern.find("{n}") == std::string::npos)
    s.report("pattern", cat("\"", source.pattern, "\" has no {n} where the slice number stands"));
  if (s.has("raw")) source.raw = parse_raw(s.child("raw"), default_channels);
  if (s.errors() != errors_before) return;
  std::error_code ec;
  if (!fs::is_directory(source.dir, ec)) {
    s.report("dir", cat("folder ", source.dir, " does not exist"));
    return;
  }
  try {
    (void)list_slices(source);
  } catch (const ConfigError& e) {
    s.report("pattern", e.what());
  }
}

void require_file(Section& s, const std::string& key, const std::string& path) {
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) s.report(key, cat("file ", path, " does not exist"));
}

// Drops every key starting with '_' (comments), recursively, for hashing.
json strip_comments(const json& value) {
  if (value.is_object()) {
    json out = json::object();
    for (auto it = value.begin(); it != value.end(); ++it)
      if (it.key().empty() || it.key()[0] != '_') out[it.key()] = strip_comments(it.value());
    return out;
  }
  if (value.is_array()) {
    json out = json::array();
    for (const auto& v : value)
      out.push_back(strip_comments(v));
    return out;
  }
  return value;
}

// The keys each object accepts (besides comments); checked before anything else so that a typo
// is reported as an unknown key rather than as the missing key it was meant to be.
const std::vector<std::pair<std::string, std::vector<std::string>>>& known_keys() {
  static const std::vector<std::pair<std::string, std::vector<std::string>>> table = {
      {"",
       {"name", "work_dir", "output", "vdb_output", "spacing_mm", "rgb", "ct", "seg", "register",
        "mask", "pack", "work", "vdb"}},
      {"rgb", {"dir", "pattern", "raw"}},
      {"ct",
       {"dir", "pattern", "raw", "pixel_spacing_mm", "slope", "intercept", "slice_spacing_mm",
        "z_offset_mm"}},
      {"seg",
       {"dir", "pattern", "raw", "palette", "mode", "tolerance", "strict", "id_map",
        "slice_spacing_mm", "z_offset_mm"}},
      {"rgb.raw",
       {"width", "height", "channels", "layout", "bits", "endian", "header_bytes", "header"}},
      {"ct.raw",
       {"width", "height", "channels", "layout", "bits", "endian", "header_bytes", "header"}},
      {"seg.raw",
       {"width", "height", "channels", "layout", "bits", "endian", "header_bytes", "header"}},
      {"register",
       {"enabled", "method", "ecc_scale", "ecc_iterations", "jump_px", "output_frame", "anchor",
        "ct_anchor_between", "overrides"}},
      {"register.output_frame", {"rotation_deg", "dx_px", "dy_px"}},
      {"mask",
       {"hu_threshold", "opening_px", "refine_gel", "gel_colour", "gel_distance", "min_part_mm2"}},
      {"pack",
       {"brick_edge", "zstd_level", "downsample", "threads", "keep_outside_body",
        "crop_margin_px"}},
      {"work", {"write_registered", "write_ct", "overlay_max_px"}},
      {"vdb", {"enabled", "level", "layout", "max_memory_mb"}},
  };
  return table;
}

// Logs every unknown key of `node` (the object at key path `path`) and below, each with the known
// key of its object nearest in spelling when one is near enough to be the key meant.
void check_unknown_keys(const json& node, const std::string& path, ErrorLog& log) {
  for (const auto& [object, keys] : known_keys()) {
    if (object != path) continue;
    if (!node.is_object()) return;  // the type error is reported by the parser
    for (auto it = node.begin(); it != node.end(); ++it) {
      const std::string& key = it.key();
      if (!key.empty() && key[0] == '_') continue;
      std::string child = path.empty() ? key : path + "." + key;
      if (std::find(keys.begin(), keys.end(), key) != keys.end()) {
        check_unknown_keys(it.value(), child, log);
        continue;
      }
      log.unknown(child);
      if (child == "ct.slice_offset") {
        // CT slices are placed along z by ct.slice_spacing_mm and ct.z_offset_mm, one way to say
        // one thing; the index offset that came before them is named with its replacement.
        log.add(child,
                "replaced by ct.z_offset_mm (CT slice k + slice_offset on colour slice k is "
                "z_offset_mm = -slice_offset x ct.slice_spacing_mm)");
        continue;
      }
      const std::string near = nearest_key(key, keys);
      if (near.empty()) {
        log.add(child, "unknown key");
        continue;
      }
      const std::string near_path = path.empty() ? near : path + "." + near;
      log.add(child, cat("unknown key (did you mean ", near_path, "?)"));
      if (!node.contains(near)) log.suggested(near_path);
    }
  }
}

// An output must never overwrite an input (docs/RELIABILITY.md). `output` and `vdb_output` may not
// be the config, the palette, or a file in a slice folder; `work_dir` may not be a slice folder.
void check_outputs_apart_from_inputs(const Config& config, const Section& top) {
  auto same = [](const std::string& a, const std::string& b) {
    std::error_code ec1, ec2;
    return fs::weakly_canonical(a, ec1) == fs::weakly_canonical(b, ec2);
  };
  std::vector<std::pair<std::string, std::string>> folders = {{"rgb.dir", config.rgb.dir}};
  if (config.ct) folders.emplace_back("ct.dir", config.ct->dir);
  if (config.seg) folders.emplace_back("seg.dir", config.seg->dir);
  std::vector<std::pair<std::string, std::string>> files = {{"the config file", config.path}};
  if (config.seg && !config.seg->palette.empty())
    files.emplace_back("seg.palette", config.seg->palette);
  std::vector<std::pair<const char*, std::string>> outputs = {{"output", config.output}};
  if (!config.vdb_output.empty()) outputs.emplace_back("vdb_output", config.vdb_output);
  for (const auto& [key, out] : outputs) {
    for (const auto& [what, in] : files)
      if (same(out, in)) top.report(key, cat(out, " is ", what, ", an input"));
    for (const auto& [what, dir] : folders)
      if (same(fs::path(out).parent_path().string(), dir))
        top.report(key, cat(out, " lies in the input slice folder ", what, " (", dir, ")"));
    std::error_code ec;
    if (fs::is_directory(out, ec)) top.report(key, cat(out, " is a folder, not a file"));
  }
  for (const auto& [what, dir] : folders)
    if (same(config.work_dir, dir))
      top.report("work_dir", cat(config.work_dir, " is the input slice folder ", what));
}

}  // namespace

std::string nearest_key(const std::string& key, const std::vector<std::string>& candidates) {
  auto lower = [](std::string text) {
    std::transform(text.begin(), text.end(), text.begin(),
                   [](unsigned char c) { return char(std::tolower(c)); });
    return text;
  };
  // Optimal string alignment distance: insertions, deletions, substitutions and swaps of two
  // neighbouring letters cost 1 each.
  auto distance = [](const std::string& a, const std::string& b) {
    const std::size_t n = a.size(), m = b.size();
    std::vector<std::vector<std::size_t>> d(n + 1, std::vector<std::size_t>(m + 1, 0));
    for (std::size_t i = 0; i <= n; ++i)
      d[i][0] = i;
    for (std::size_t j = 0; j <= m; ++j)
      d[0][j] = j;
    for (std::size_t i = 1; i <= n; ++i)
      for (std::size_t j = 1; j <= m; ++j) {
        const std::size_t cost = a[i - 1] == b[j - 1] ? 0 : 1;
        d[i][j] = std::min({d[i - 1][j] + 1, d[i][j - 1] + 1, d[i - 1][j - 1] + cost});
        if (i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1])
          d[i][j] = std::min(d[i][j], d[i - 2][j - 2] + 1);
      }
    return d[n][m];
  };
  const std::string wanted = lower(key);
  std::string best;
  std::size_t best_distance = std::numeric_limits<std::size_t>::max();
  for (const auto& candidate : candidates) {
    const std::string c = lower(candidate);
    const std::size_t d = distance(wanted, c);
    const bool prefix = wanted.size() >= 3 && c.compare(0, wanted.size(), wanted) == 0;
    const bool near =
        (d <= 2 && wanted.size() >= 4) || 3 * d <= std::max(wanted.size(), c.size()) || prefix;
    if (near && d < best_distance) {
      best = candidate;
      best_distance = d;
    }
  }
  return best;
}

std::vector<std::string> config_key_paths() {
  std::vector<std::string> out;
  for (const auto& [object, keys] : known_keys())
    for (const auto& key : keys)
      out.push_back(object.empty() ? key : object + "." + key);
  return out;
}

namespace {

// The "ct" section (absent or null: no CT); `base` resolves its folder.
void parse_ct_section(Section& top, Config& config, const std::string& base) {
  if (top.has("ct") && !config.raw_json["ct"].is_null()) {
    Section s = top.child("ct");
    CtSource ct;
    parse_source(s, ct, base, "ct_{n}.png", 1);
    ct.pixel_spacing_mm = s.numbers<2>("pixel_spacing_mm", std::nullopt, 0.0, 1e6, true);
    if (ct.raw && ct.raw->genesis) ct.raw->genesis_pixel_mm = ct.pixel_spacing_mm;
    ct.slope = s.number("slope", 1.0, -1e6, 1e6);
    if (ct.slope == 0) s.report("slope", "must not be 0");
    ct.intercept = s.number("intercept", -1024.0, -1e6, 1e6);
    ct.slice_spacing_mm = s.number("slice_spacing_mm", config.spacing_mm[2], 0.0, 1e6, true);
    ct.z_offset_mm = s.number("z_offset_mm", 0.0, -1e9, 1e9);
    s.finish();
    config.ct = ct;
  } else {
    top.find("ct");
  }
}

// The "seg" section (absent or null: no segmentation).
void parse_seg_section(Section& top, Config& config, const std::string& base) {
  if (top.has("seg") && !config.raw_json["seg"].is_null()) {
    Section s = top.child("seg");
    SegSource seg;
    parse_source(s, seg, base, "seg_{n}.png", 3);
    seg.mode = s.choice("mode", {"colour", "id"}, "colour");
    if (s.has("palette")) {
      seg.palette = resolve(base, s.string("palette", std::nullopt));
      require_file(s, "palette", seg.palette);
    } else if (seg.mode == "colour") {
      s.report_missing("palette", "missing (required in mode \"colour\")");
    } else {
      s.find("palette");
    }
    seg.tolerance = s.number("tolerance", 24.0, 0.0, 442.0);
    seg.strict = s.boolean("strict", false);
    if (s.has("slice_spacing_mm")) {
      seg.slice_spacing_mm = s.number("slice_spacing_mm", std::nullopt, 0.0, 1e6, true);
      seg.z_offset_mm = s.number("z_offset_mm", 0.0, -1e9, 1e9);
    } else if (s.has("z_offset_mm")) {
      s.report("z_offset_mm",
               "needs seg.slice_spacing_mm (without it segmentation slices are matched to colour "
               "slices by file number)");
    }
    if (s.has("id_map")) {
      if (seg.mode != "id") s.report("id_map", "only allowed in mode \"id\"");
      seg.id_map = resolve(base, s.string("id_map", std::nullopt));
      require_file(s, "id_map", seg.id_map);
    } else {
      s.find("id_map");
    }
    s.finish();
    config.seg = seg;
  } else {
    top.find("seg");
  }
}

// The "register" section (checked against the CT section: anchor "ct" needs one).
void parse_register_section(Section& top, Config& config, const std::string& base) {
  Section s = top.child("register");
  auto& r = config.registration;
  r.enabled = s.boolean("enabled", true);
  r.method = s.choice("method", {"phase", "phase+ecc", "none"}, "phase+ecc");
  r.ecc_scale = s.number("ecc_scale", 0.5, 0.0, 1.0, true);
  r.ecc_iterations = int(s.integer("ecc_iterations", 50, 1, 10000));
  r.jump_px = s.number("jump_px", 6.0, 0.0, 1e6, true);
  if (s.has("output_frame")) {
    Section f = s.child("output_frame");
    r.output_frame.rotation_deg = f.number("rotation_deg", 0.0, -360.0, 360.0);
    r.output_frame.dx_px = f.number("dx_px", 0.0, -1e6, 1e6);
    r.output_frame.dy_px = f.number("dy_px", 0.0, -1e6, 1e6);
    f.finish();
  } else {
    s.find("output_frame");
  }
  r.anchor = s.choice("anchor", {"auto", "ct", "fiducials", "none"}, "auto");
  r.ct_anchor_between = s.choice("ct_anchor_between", {"nearest", "interpolated"}, "nearest");
  if (r.anchor == "ct" && !(top.has("ct") && !config.raw_json["ct"].is_null()))
    s.report("anchor", "\"ct\" needs a \"ct\" section (CT slices)");
  if (s.has("overrides")) {
    r.overrides = resolve(base, s.string("overrides", std::nullopt));
    require_file(s, "overrides", r.overrides);
  } else {
    s.find("overrides");
  }
  s.finish();
}

void parse_mask_section(Section& top, Config& config) {
  Section s = top.child("mask");
  auto& m = config.mask;
  m.hu_threshold = s.number("hu_threshold", -400.0, -2000.0, 5000.0);
  m.opening_px = int(s.integer("opening_px", 1, 0, 64));
  m.refine_gel = s.boolean("refine_gel", true);
  if (s.has("gel_colour")) {
    auto c = s.numbers<3>("gel_colour", std::nullopt, 0.0, 255.0, false);
    std::array<int, 3> gel{};
    for (int i = 0; i < 3; ++i) {
      if (c[i] != std::floor(c[i])) s.report(cat("gel_colour[", i, "]"), "must be an integer");
      gel[i] = int(c[i]);
    }
    m.gel_colour = gel;
  } else {
    s.find("gel_colour");
  }
  m.gel_distance = s.number("gel_distance", 40.0, 0.0, 442.0);
  m.min_part_mm2 = s.number("min_part_mm2", 5.0, 0.0, 1e6);
  s.finish();
}

void parse_pack_section(Section& top, Config& config) {
  Section s = top.child("pack");
  auto& p = config.pack;
  p.brick_edge = int(s.integer("brick_edge", 64, 8, 256));
  if ((p.brick_edge & (p.brick_edge - 1)) != 0)
    s.report("brick_edge", cat(p.brick_edge, " is not a power of two"));
  p.zstd_level = int(s.integer("zstd_level", 3, 0, 22));
  p.downsample = int(s.integer("downsample", 1, 1, 64));
  p.threads = int(s.integer("threads", 0, 0, 4096));
  const std::string keep = s.choice("keep_outside_body", {"none", "colour", "ct", "all"}, "none");
  p.keep_colour_outside_body = keep == "colour" || keep == "all";
  p.keep_ct_outside_body = keep == "ct" || keep == "all";
  if (s.has("crop_margin_px")) {
    if (config.raw_json["pack"]["crop_margin_px"].is_null()) {
      s.find("crop_margin_px");  // null: no crop, as when absent
    } else {
      p.crop_margin_px = int(s.integer("crop_margin_px", std::nullopt, 0, 65536));
    }
  } else {
    s.find("crop_margin_px");
  }
  s.finish();
}

void parse_work_section(Section& top, Config& config) {
  Section s = top.child("work");
  auto& w = config.work;
  w.write_registered = s.boolean("write_registered", false);
  w.write_ct = s.boolean("write_ct", false);
  w.overlay_max_px = int(s.integer("overlay_max_px", 1024, 0, 65536));
  if (w.overlay_max_px > 0 && w.overlay_max_px < 16)
    s.report("overlay_max_px", cat(w.overlay_max_px, " is too small (0 = full size, else >= 16)"));
  s.finish();
}

void parse_vdb_section(Section& top, Config& config) {
  Section s = top.child("vdb");
  config.vdb.enabled = s.boolean("enabled", true);
  if (const json* level = s.find("level"); level && !level->is_null()) {
    if (level->is_string()) {
      if (level->get<std::string>() != "auto")
        s.report("level",
                 cat("\"", level->get<std::string>(), "\" is not a level (0..15 or \"auto\")"));
    } else {
      config.vdb.level = int(s.integer("level", 0, 0, 15));
    }
  }
  const std::string layout = s.string("layout", "auto");
  if (layout == "file")
    config.vdb.layout = VdbLayout::kFile;
  else if (layout != "auto")
    s.report("layout", cat("\"", layout, "\" is not a layout (\"auto\" or \"file\")"));
  config.vdb.max_memory_mb = s.integer("max_memory_mb", 1024, 16, std::int64_t(1) << 30);
  s.finish();
}

}  // namespace

Config load_config(const std::string& path) {
  Config config;
  std::error_code ec;
  fs::path absolute = fs::absolute(path, ec);
  config.path = absolute.lexically_normal().string();
  std::string text = read_file(config.path, std::size_t(64) << 20);
  try {
    // Comments (// and /* */) are allowed, as are "_comment" keys.
    config.raw_json = json::parse(text, nullptr, true, /*ignore_comments=*/true);
  } catch (const json::exception& e) {  // parse_error, and out_of_range for a number overflow
    throw ConfigError(cat(config.path, ": not valid JSON: ", e.what()));
  }
  const std::string& file = config.path;
  const std::string base = fs::path(config.path).parent_path().string();
  if (!config.raw_json.is_object())
    throw ConfigError(
        cat(file, ": (top level): must be an object, got ", type_name(config.raw_json)));
  // Every error is logged and the checks go on, so that one run lists them all.
  ErrorLog log(file);
  check_unknown_keys(config.raw_json, "", log);
  Section top(config.raw_json, "", log, file);

  config.name = top.string("name", fs::path(config.path).stem().string());
  if (config.name.empty()) top.report("name", "must not be empty");
  config.work_dir = resolve(base, top.string("work_dir", "work"));
  config.output = resolve(base, top.string("output", "out/" + config.name + ".vpk"));
  config.spacing_mm = top.numbers<3>("spacing_mm", std::nullopt, 0.0, 1e6, true);

  if (top.has("rgb")) {
    Section s = top.child("rgb");
    parse_source(s, config.rgb, base, "rgb_{n}.png", 3);
    s.finish();
  } else {
    top.find("rgb");
    top.report_missing("rgb", "missing (required)");
  }
  parse_ct_section(top, config, base);
  parse_seg_section(top, config, base);
  parse_register_section(top, config, base);
  parse_mask_section(top, config);
  parse_pack_section(top, config);
  parse_work_section(top, config);
  parse_vdb_section(top, config);
  std::string default_vdb = fs::path(config.output).replace_extension(".vdb").string();
  std::string vdb_output = top.string("vdb_output", default_vdb);
  config.vdb_output = config.vdb.enabled ? resolve(base, vdb_output) : "";
  if (config.vdb.enabled && config.vdb_output == config.output)
    top.report("vdb_output", "must differ from output");
  // Outputs against inputs: only once every path is known to be sound.
  if (log.count() == 0) check_outputs_apart_from_inputs(config, top);
  top.finish();
  log.throw_if_any();
  return config;
}

namespace {

// `path` relative to `base` when both are absolute and a relative form exists; else as is.
std::string relative_to(const std::string& path, const std::string& base) {
  if (path.empty() || base.empty()) return path;
  const fs::path p(path), b(base);
  if (!p.is_absolute() || !b.is_absolute()) return path;
  const fs::path rel = p.lexically_relative(b);
  return rel.empty() ? path : rel.generic_string();
}

json raw_to_json(const RawLayout& raw) {
  json out = {{"width", raw.width},
              {"height", raw.height},
              {"channels", raw.channels},
              {"layout", raw.planar ? "planar" : "interleaved"},
              {"bits", raw.bits},
              {"endian", raw.big_endian ? "big" : "little"},
              {"header_bytes", raw.header_bytes}};
  if (raw.genesis) out["header"] = "genesis";
  return out;
}

json source_to_json(const SliceSource& source, const std::string& base) {
  json out = {{"dir", relative_to(source.dir, base)}, {"pattern", source.pattern}};
  if (source.raw) out["raw"] = raw_to_json(*source.raw);
  return out;
}

}  // namespace

json config_to_json(const Config& config) {
  return config_to_json(config, fs::path(config.path).parent_path().string());
}

json config_to_json(const Config& config, const std::string& base_dir) {
  const std::string& base = base_dir;
  json out = json::object();
  out["name"] = config.name;
  out["work_dir"] = relative_to(config.work_dir, base);
  out["output"] = relative_to(config.output, base);
  if (config.vdb.enabled && !config.vdb_output.empty())
    out["vdb_output"] = relative_to(config.vdb_output, base);
  out["spacing_mm"] = config.spacing_mm;
  out["rgb"] = source_to_json(config.rgb, base);
  if (config.ct) {
    const CtSource& ct = *config.ct;
    json c = source_to_json(ct, base);
    c["pixel_spacing_mm"] = ct.pixel_spacing_mm;
    c["slope"] = ct.slope;
    c["intercept"] = ct.intercept;
    c["slice_spacing_mm"] = ct.slice_spacing_mm.value_or(config.spacing_mm[2]);
    c["z_offset_mm"] = ct.z_offset_mm;
    out["ct"] = c;
  }
  if (config.seg) {
    const SegSource& seg = *config.seg;
    json s = source_to_json(seg, base);
    if (!seg.palette.empty()) s["palette"] = relative_to(seg.palette, base);
    s["mode"] = seg.mode;
    s["tolerance"] = seg.tolerance;
    s["strict"] = seg.strict;
    if (!seg.id_map.empty()) s["id_map"] = relative_to(seg.id_map, base);
    if (seg.slice_spacing_mm) {
      s["slice_spacing_mm"] = *seg.slice_spacing_mm;
      s["z_offset_mm"] = seg.z_offset_mm;
    }
    out["seg"] = s;
  }
  const RegisterOptions& r = config.registration;
  out["register"] = {{"enabled", r.enabled},
                     {"method", r.method},
                     {"ecc_scale", r.ecc_scale},
                     {"ecc_iterations", r.ecc_iterations},
                     {"jump_px", r.jump_px},
                     {"output_frame",
                      {{"rotation_deg", r.output_frame.rotation_deg},
                       {"dx_px", r.output_frame.dx_px},
                       {"dy_px", r.output_frame.dy_px}}},
                     {"anchor", r.anchor},
                     {"ct_anchor_between", r.ct_anchor_between}};
  if (!r.overrides.empty()) out["register"]["overrides"] = relative_to(r.overrides, base);
  const MaskOptions& m = config.mask;
  json mask = {{"hu_threshold", m.hu_threshold},
               {"opening_px", m.opening_px},
               {"refine_gel", m.refine_gel},
               {"gel_distance", m.gel_distance},
               {"min_part_mm2", m.min_part_mm2}};
  if (m.gel_colour) mask["gel_colour"] = *m.gel_colour;
  out["mask"] = mask;
  out["pack"] = {{"brick_edge", config.pack.brick_edge},
                 {"zstd_level", config.pack.zstd_level},
                 {"downsample", config.pack.downsample},
                 {"threads", config.pack.threads}};
  const PackOptions& p = config.pack;
  out["pack"]["keep_outside_body"] = p.keep_colour_outside_body
                                         ? (p.keep_ct_outside_body ? "all" : "colour")
                                         : (p.keep_ct_outside_body ? "ct" : "none");
  if (p.crop_margin_px) out["pack"]["crop_margin_px"] = *p.crop_margin_px;
  out["work"] = {{"write_registered", config.work.write_registered},
                 {"write_ct", config.work.write_ct},
                 {"overlay_max_px", config.work.overlay_max_px}};
  out["vdb"] = {{"enabled", config.vdb.enabled}, {"max_memory_mb", config.vdb.max_memory_mb}};
  out["vdb"]["level"] = config.vdb.level ? json(*config.vdb.level) : json("auto");
  out["vdb"]["layout"] = config.vdb.layout == VdbLayout::kFile ? "file" : "auto";
  return out;
}

void write_config(const std::string& path, const Config& config) {
  const std::string base = fs::path(fs::absolute(path)).lexically_normal().parent_path().string();
  write_file_atomic(path, config_to_json(config, base).dump(2) + "\n");
}

std::string config_section_hash(const Config& config, const std::vector<std::string>& sections) {
  std::string data;
  for (const auto& name : sections) {
    // "mask" hashes a whole section; "mask.hu_threshold" one key inside it.
    const json* node = &config.raw_json;
    std::size_t begin = 0;
    while (node && begin <= name.size()) {
      std::size_t dot = name.find('.', begin);
      std::string part =
          name.substr(begin, dot == std::string::npos ? std::string::npos : dot - begin);
      node = node->is_object() && node->contains(part) ? &(*node)[part] : nullptr;
      if (dot == std::string::npos) break;
      begin = dot + 1;
    }
    json value = node ? strip_comments(*node) : json();
    data += name + "=" + value.dump() + "\n";
  }
  return hex64(xxh64(data.data(), data.size()));
}

}  // namespace vispack::pipeline

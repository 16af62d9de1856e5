#include "vispack/format/metadata.h"

#include <cmath>
#include <limits>
#include <optional>
#include <unordered_set>

#include "int_math.h"
#include "vispack/common/error.h"

namespace vispack::format {
namespace {

using nlohmann::json;

using detail::mul;

template <typename T>
json array3(const std::array<T, 3>& a) {
  return json::array({a[0], a[1], a[2]});
}

// Rejects JSON nested deeper than kMaxMetadataDepth before the parser sees it.
void check_json_depth(const std::string& path, const char* text, std::size_t size) {
  int depth = 0;
  bool in_string = false, escape = false;
  for (std::size_t i = 0; i < size; ++i) {
    char ch = text[i];
    if (in_string) {
      if (escape)
        escape = false;
      else if (ch == '\\')
        escape = true;
      else if (ch == '"')
        in_string = false;
      continue;
    }
    if (ch == '"')
      in_string = true;
    else if (ch == '[' || ch == '{') {
      if (++depth > kMaxMetadataDepth) {
        throw FormatError(cat(path, ": metadata JSON nested deeper than ", kMaxMetadataDepth,
                              " levels (at byte ", i, ")"));
      }
    } else if (ch == ']' || ch == '}') {
      --depth;
    }
  }
}

// Typed access to metadata keys with one clear error per bad key.
class MetaReader {
 public:
  explicit MetaReader(const std::string& path) : path_(path) {}

  const json& get(const json& obj, const std::string& key) const {
    if (!obj.is_object()) fail(key, cat("parent of \"", key, "\" is not an object"));
    auto it = obj.find(key);
    if (it == obj.end()) fail(key, "is missing");
    return *it;
  }
  std::int64_t integer(const json& v, const std::string& key, std::int64_t lo,
                       std::int64_t hi) const {
    if (!v.is_number_integer()) fail(key, "is not an integer");
    if (v.is_number_unsigned() && v.get<std::uint64_t>() > std::uint64_t(hi)) {
      fail(key, cat("= ", v.get<std::uint64_t>(), " is outside [", lo, ", ", hi, "]"));
    }
    std::int64_t x = v.get<std::int64_t>();
    if (x < lo || x > hi) fail(key, cat("= ", x, " is outside [", lo, ", ", hi, "]"));
    return x;
  }
  double number(const json& v, const std::string& key) const {
    if (!v.is_number()) fail(key, "is not a number");
    double x = v.get<double>();
    if (!std::isfinite(x)) fail(key, "is not finite");
    return x;
  }
  std::string string(const json& v, const std::string& key) const {
    if (!v.is_string()) fail(key, "is not a string");
    return v.get<std::string>();
  }
  const json& array(const json& v, const std::string& key, std::size_t min_size,
                    std::size_t max_size) const {
    if (!v.is_array()) fail(key, "is not an array");
    if (v.size() < min_size || v.size() > max_size) {
      fail(key, cat("has ", v.size(), " elements, expected ", min_size, "..", max_size));
    }
    return v;
  }
  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    throw FormatError(cat(path_, ": metadata key \"", key, "\" ", what));
  }

 private:
  const std::string& path_;
};

}  // namespace

const char* downsample_rule(ChannelType type) {
  switch (type) {
    case ChannelType::kRgba8:
      return "alpha_weighted_mean";
    case ChannelType::kInt16:
      return "mean";
    default:
      return "majority";
  }
}

json metadata_json(const VolumeMetadata& meta, const VolumeGeometry& geometry) {
  json m = json::object();
  m["format"] = "vispack";
  m["version"] = json::array({kFormatMajor, kFormatMinor});
  m["dims"] = array3(meta.dims);
  m["spacing_mm"] = array3(meta.spacing_mm);
  m["origin_mm"] = array3(meta.origin_mm);
  m["axes"] = json::array({"x: image column, left to right", "y: image row, top to bottom",
                           "z: slice index, increasing"});
  m["memory_order"] = "x fastest, then y, then z; components interleaved";
  m["brick_edge"] = meta.brick_edge;
  m["brick_padding"] = "replicate";
  json channels = json::array();
  for (const auto& s : meta.channels) {
    channels.push_back({{"name", s.name},
                        {"type", channel_type_name(s.type)},
                        {"components", channel_type_components(s.type)},
                        {"downsample", downsample_rule(s.type)}});
  }
  m["channels"] = channels;
  json lv = json::array();
  for (const LevelInfo& li : geometry.levels) {
    lv.push_back({{"dims", array3(li.dims)},
                  {"bricks", array3(li.bricks)},
                  {"spacing_mm", array3(li.spacing_mm)},
                  {"origin_mm", array3(li.origin_mm)}});
  }
  m["levels"] = lv;
  json table = json::array();
  for (const auto& l : meta.label_table) {
    table.push_back({{"id", l.id},
                     {"name", l.name},
                     {"colour", json::array({l.colour[0], l.colour[1], l.colour[2]})}});
  }
  m["label_table"] = table;
  m["extra"] = meta.extra.is_null() ? json::object() : meta.extra;
  return m;
}

VolumeMetadata parse_metadata(const std::string& path, const char* text, std::size_t size,
                              const ReaderLimits& limits, json* root) {
  check_json_depth(path, text, size);
  json doc;
  try {
    doc = json::parse(text, text + size);
  } catch (const json::exception& e) {
    throw FormatError(cat(path, ": malformed metadata JSON: ", e.what()));
  }
  if (!doc.is_object()) throw FormatError(cat(path, ": metadata JSON is not an object"));
  MetaReader r(path);
  VolumeMetadata out;
  if (r.string(r.get(doc, "format"), "format") != "vispack") r.fail("format", "is not \"vispack\"");
  const json& dims_j = r.array(r.get(doc, "dims"), "dims", 3, 3);
  for (int a = 0; a < 3; ++a)
    out.dims[a] = r.integer(dims_j[a], "dims", 1, limits.max_dim);
  auto voxels = mul(std::uint64_t(out.dims[0]), std::uint64_t(out.dims[1]));
  if (voxels) voxels = mul(*voxels, std::uint64_t(out.dims[2]));
  if (!voxels || *voxels > limits.max_level_voxels) {
    r.fail("dims", cat(out.dims[0], "x", out.dims[1], "x", out.dims[2], " exceed the limit of ",
                       limits.max_level_voxels, " voxels"));
  }
  const json& sp = r.array(r.get(doc, "spacing_mm"), "spacing_mm", 3, 3);
  const json& org = r.array(r.get(doc, "origin_mm"), "origin_mm", 3, 3);
  for (int a = 0; a < 3; ++a) {
    out.spacing_mm[a] = r.number(sp[a], "spacing_mm");
    if (!(out.spacing_mm[a] > 0)) r.fail("spacing_mm", "has a value <= 0");
    out.origin_mm[a] = r.number(org[a], "origin_mm");
  }
  out.brick_edge = int(r.integer(r.get(doc, "brick_edge"), "brick_edge", 4, 1024));
  const json& ch = r.array(r.get(doc, "channels"), "channels", 1, 255);
  std::unordered_set<std::string> names;
  for (const json& c : ch) {
    ChannelSpec s;
    s.name = r.string(r.get(c, "name"), "channels[].name");
    if (s.name.empty() || !names.insert(s.name).second)
      r.fail("channels[].name", cat("\"", s.name, "\" is empty or repeated"));
    try {
      s.type = channel_type_from_name(r.string(r.get(c, "type"), "channels[].type"));
    } catch (const FormatError& e) {
      r.fail("channels[].type", e.what());
    }
    out.channels.push_back(s);
  }
  if (doc.contains("label_table")) {
    const json& lt = r.array(doc["label_table"], "label_table", 0, 65535);
    for (const json& l : lt) {
      LabelEntry e;
      e.id = std::uint32_t(r.integer(r.get(l, "id"), "label_table[].id", 1, 65535));
      e.name = r.string(r.get(l, "name"), "label_table[].name");
      const json& col = r.array(r.get(l, "colour"), "label_table[].colour", 3, 3);
      for (int k = 0; k < 3; ++k)
        e.colour[k] = std::uint8_t(r.integer(col[k], "label_table[].colour", 0, 255));
      out.label_table.push_back(std::move(e));
    }
  }
  if (doc.contains("extra")) out.extra = doc["extra"];
  if (root) *root = std::move(doc);
  return out;
}

}  // namespace vispack::format

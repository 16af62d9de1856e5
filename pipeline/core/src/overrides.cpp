// read_overrides and its JSON form (overrides.h).
#include "vispack/pipeline/core/overrides.h"

#include <set>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"

namespace vispack::pipeline {

std::vector<SliceOverride> read_overrides(const std::string& path, int slice_count) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(read_file(path, std::size_t(1) << 26));
  } catch (const nlohmann::json::parse_error& e) {
    throw ConfigError(cat(path, ": register.overrides: not valid JSON: ", e.what()));
  }
  auto fail = [&](const std::string& key, const std::string& message) {
    throw ConfigError(cat(path, ": ", key, ": ", message));
  };
  if (!j.is_object()) fail("(top level)", "must be an object");
  for (auto it = j.begin(); it != j.end(); ++it)
    if (it.key() != "slices" && (it.key().empty() || it.key()[0] != '_'))
      fail(it.key(), "unknown key");
  std::vector<SliceOverride> out;
  if (!j.contains("slices")) return out;
  if (!j["slices"].is_array()) fail("slices", "must be an array");
  std::vector<bool> seen(std::size_t(std::max(slice_count, 0)), false);
  for (std::size_t i = 0; i < j["slices"].size(); ++i) {
    const auto& e = j["slices"][i];
    const std::string where = cat("slices[", i, "]");
    if (!e.is_object()) fail(where, "must be an object");
    SliceOverride o;
    for (auto it = e.begin(); it != e.end(); ++it) {
      const std::string& key = it.key();
      const auto& v = it.value();
      const std::string kp = where + "." + key;
      if (!key.empty() && key[0] == '_') continue;
      if (key == "index") {
        if (!v.is_number_integer()) fail(kp, "must be an integer");
        o.index = v.get<int>();
        if (o.index < 0 || o.index >= slice_count)
          fail(kp, cat(o.index, " is outside the stack [0, ", slice_count, ")"));
      } else if (key == "transform") {
        if (!v.is_object()) fail(kp, "must be an object");
        Rigid r;
        for (auto t = v.begin(); t != v.end(); ++t) {
          if (!t.value().is_number() || !std::isfinite(t.value().get<double>()))
            fail(kp + "." + t.key(), "must be a finite number");
          const double x = t.value().get<double>();
          if (t.key() == "rotation_deg") {
            r.rotation_deg = x;
          } else if (t.key() == "dx_px") {
            r.dx_px = x;
          } else if (t.key() == "dy_px") {
            r.dy_px = x;
          } else if (t.key().empty() || t.key()[0] != '_') {
            fail(kp + "." + t.key(), "unknown key");
          }
        }
        o.transform = r;
      } else if (key == "jump") {
        if (!v.is_boolean()) fail(kp, "must be true or false");
        o.jump = v.get<bool>();
      } else if (key == "anchor") {
        if (!v.is_boolean()) fail(kp, "must be true or false");
        o.exclude_anchor = !v.get<bool>();
      } else if (key == "note") {
        if (!v.is_string()) fail(kp, "must be a string");
        o.note = v.get<std::string>();
      } else {
        fail(kp, "unknown key");
      }
    }
    if (!e.contains("index")) fail(where + ".index", "missing (required)");
    if (seen[std::size_t(o.index)])
      fail(where + ".index", cat("slice ", o.index, " is listed twice"));
    seen[std::size_t(o.index)] = true;
    out.push_back(o);
  }
  return out;
}

nlohmann::json to_json(const SliceOverride& o) {
  nlohmann::json j = {{"index", o.index}};
  if (o.transform)
    j["transform"] = {{"rotation_deg", o.transform->rotation_deg},
                      {"dx_px", o.transform->dx_px},
                      {"dy_px", o.transform->dy_px}};
  if (o.jump) j["jump"] = true;
  if (o.exclude_anchor) j["anchor"] = false;
  if (!o.note.empty()) j["note"] = o.note;
  return j;
}

// ---- the CT-anchored solve ----
}  // namespace vispack::pipeline

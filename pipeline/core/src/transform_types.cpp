// transforms.json. See core/transform_types.h.
#include "vispack/pipeline/core/transform_types.h"

#include <filesystem>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

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
  if (j.contains("reference_slice") && !j["reference_slice"].is_null())
    t.reference_slice = get_key<int>(j, "reference_slice", path, 0, true);
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
    st.rigid.dx_px = get_key<double>(s, "dx_px", where, 0.0, true);
    st.rigid.dy_px = get_key<double>(s, "dy_px", where, 0.0, true);
    st.rigid.rotation_deg = get_key<double>(s, "rotation_deg", where, 0.0, true);
    st.jump = get_key<bool>(s, "jump", where, false, false);
    st.black = get_key<bool>(s, "black", where, false, false);
    if (s.contains("duplicate_of") && !s["duplicate_of"].is_null())
      st.duplicate_of = get_key<int>(s, "duplicate_of", where, 0, true);
    st.quality = get_key<double>(s, "quality", where, 1.0, false);
    for (auto& [key, value] : s.items()) {
      if (key != "index" && key != "number" && key != "file" && key != "dx_px" && key != "dy_px" &&
          key != "rotation_deg" && key != "jump" && key != "black" && key != "duplicate_of" &&
          key != "quality")
        st.extra[key] = value;
    }
    if (!std::isfinite(st.rigid.dx_px) || !std::isfinite(st.rigid.dy_px) ||
        !std::isfinite(st.rigid.rotation_deg))
      throw FormatError(cat(where, ": transform is not finite"));
    t.slices.push_back(st);
  }
  if (j.contains("ct_to_rgb") && !j["ct_to_rgb"].is_null()) {
    const auto& c = j["ct_to_rgb"];
    std::string where = cat(path, ": ct_to_rgb");
    if (!c.is_object()) throw FormatError(cat(where, ": not an object"));
    Similarity ct;
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

std::string transforms_text(const StackTransforms& t) {
  nlohmann::json j = t.extra.is_object() ? t.extra : nlohmann::json::object();
  j["width"] = t.width;
  j["height"] = t.height;
  j["center_px"] = t.center_px;
  j["reference_slice"] = t.reference_slice ? nlohmann::json(*t.reference_slice) : nlohmann::json();
  nlohmann::json slices = nlohmann::json::array();
  for (const auto& s : t.slices) {
    nlohmann::json slice = s.extra.is_object() ? s.extra : nlohmann::json::object();
    slice["index"] = s.index;
    slice["number"] = s.number;
    slice["file"] = s.file;
    slice["dx_px"] = s.rigid.dx_px;
    slice["dy_px"] = s.rigid.dy_px;
    slice["rotation_deg"] = s.rigid.rotation_deg;
    slice["jump"] = s.jump;
    slice["black"] = s.black;
    slice["duplicate_of"] = s.duplicate_of ? nlohmann::json(*s.duplicate_of) : nlohmann::json();
    slice["quality"] = s.quality;
    slices.push_back(std::move(slice));
  }
  j["slices"] = std::move(slices);
  if (t.ct_to_rgb) {
    j["ct_to_rgb"] = {{"scale", t.ct_to_rgb->scale},
                      {"rotation_deg", t.ct_to_rgb->rotation_deg},
                      {"dx_px", t.ct_to_rgb->dx_px},
                      {"dy_px", t.ct_to_rgb->dy_px}};
  }
  return j.dump(2) + "\n";
}

void write_transforms(const std::string& path, const StackTransforms& t) {
  make_directories(fs::path(path).parent_path().string());
  write_file_atomic(path, transforms_text(t));
}

}  // namespace vispack::pipeline

// read_palette and read_id_map (palette.h): the label tables.
#include <cstdlib>
#include <map>
#include <set>

#include <nlohmann/json.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/core/palette.h"

namespace vispack::pipeline {

using nlohmann::json;

std::vector<PaletteEntry> read_palette(const std::string& path) {
  json j;
  try {
    j = json::parse(read_file(path, std::size_t(256) << 20), nullptr, true, true);
  } catch (const json::parse_error& e) {
    throw FormatError(cat(path, ": not valid JSON: ", e.what()));
  }
  const json* list = nullptr;
  if (j.is_object() && j.contains("labels")) list = &j["labels"];
  if (!list || !list->is_array()) throw FormatError(cat(path, ": expected {\"labels\": [...]}"));
  std::vector<PaletteEntry> out;
  std::set<std::uint32_t> ids;
  std::map<std::uint32_t, std::uint32_t> colours;
  for (std::size_t i = 0; i < list->size(); ++i) {
    const json& e = (*list)[i];
    std::string where = cat(path, ": labels[", i, "]");
    if (!e.is_object()) throw FormatError(cat(where, ": not an object"));
    PaletteEntry entry;
    if (!e.contains("id") || !e["id"].is_number_integer() || e["id"].get<long long>() < 0 ||
        e["id"].get<long long>() > 65535)
      throw FormatError(cat(where, ": \"id\" must be an integer in 0..65535"));
    entry.id = std::uint16_t(e["id"].get<long long>());
    if (e.contains("name")) {
      if (!e["name"].is_string()) throw FormatError(cat(where, ": \"name\" must be a string"));
      entry.name = e["name"].get<std::string>();
    }
    const json& c = e.contains("colour") ? e["colour"] : e.value("color", json());
    if (!c.is_array() || c.size() != 3)
      throw FormatError(cat(where, ": \"colour\" must be [r, g, b]"));
    for (int k = 0; k < 3; ++k) {
      if (!c[k].is_number_integer() || c[k].get<long long>() < 0 || c[k].get<long long>() > 255)
        throw FormatError(cat(where, ": colour component ", k, " must be an integer in 0..255"));
      entry.colour[k] = std::uint8_t(c[k].get<int>());
    }
    if (!ids.insert(entry.id).second) throw FormatError(cat(where, ": duplicate id ", entry.id));
    std::uint32_t key = pack_rgb(entry.colour[0], entry.colour[1], entry.colour[2]);
    auto [it, fresh] = colours.emplace(key, entry.id);
    if (!fresh)
      throw FormatError(cat(where, ": colour [", int(entry.colour[0]), ", ", int(entry.colour[1]),
                            ", ", int(entry.colour[2]), "] is already used by id ", it->second));
    out.push_back(std::move(entry));
  }
  return out;
}

std::unordered_map<std::uint32_t, std::uint16_t> read_id_map(const std::string& path) {
  json j;
  try {
    j = json::parse(read_file(path, std::size_t(256) << 20), nullptr, true, true);
  } catch (const json::parse_error& e) {
    throw FormatError(cat(path, ": not valid JSON: ", e.what()));
  }
  if (!j.is_object())
    throw FormatError(cat(path, ": expected an object {\"<input id>\": <output id>}"));
  std::unordered_map<std::uint32_t, std::uint16_t> out;
  for (auto& [key, value] : j.items()) {
    if (!key.empty() && key[0] == '_') continue;
    char* end = nullptr;
    long in = std::strtol(key.c_str(), &end, 10);
    if (key.empty() || *end != '\0' || in < 0 || in > 65535)
      throw FormatError(cat(path, ": key \"", key, "\" is not an ID in 0..65535"));
    if (!value.is_number_integer() || value.get<long long>() < 0 || value.get<long long>() > 65535)
      throw FormatError(cat(path, ": \"", key, "\": value must be an ID in 0..65535"));
    out[std::uint32_t(in)] = std::uint16_t(value.get<int>());
  }
  return out;
}

}  // namespace vispack::pipeline

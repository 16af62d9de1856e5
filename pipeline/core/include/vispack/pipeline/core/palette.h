// The label tables: palette.json (ID, name, colour) and id_map JSON files (labels.h describes
// both formats and how the labels stage uses them). Reads no image (vispack-merge links it).
// Thread-safe: pure functions.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <unordered_map>
#include <vector>

namespace vispack::pipeline {

struct PaletteEntry {
  std::uint16_t id = 0;
  std::string name;
  std::array<std::uint8_t, 3> colour{0, 0, 0};
};

// The key of colour (r, g, b) in the palette's lookups: 0xRRGGBB.
inline std::uint32_t pack_rgb(int r, int g, int b) {
  return (std::uint32_t(r) << 16) | (std::uint32_t(g) << 8) | std::uint32_t(b);
}

// Reads palette.json. Throws FormatError naming the file and entry (bad id, duplicate id,
// duplicate colour, colour out of 0..255), IoError if unreadable.
std::vector<PaletteEntry> read_palette(const std::string& path);

// Reads an id_map JSON {"<input id>": <output id>} (IDs 0..65535). Throws FormatError / IoError.
std::unordered_map<std::uint32_t, std::uint16_t> read_id_map(const std::string& path);

}  // namespace vispack::pipeline

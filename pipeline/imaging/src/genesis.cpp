// GE Genesis (Signa 5.x) image header: the fixed part (genesis.h).
#include "vispack/pipeline/imaging/genesis.h"

#include <cctype>
#include <cmath>
#include <cstring>

#include "vispack/common/error.h"

namespace vispack::pipeline {
namespace {

std::int64_t big_endian_int32(std::string_view head, std::size_t at) {
  std::uint32_t v = 0;
  for (std::size_t i = 0; i < 4; ++i)
    v = v << 8 | std::uint8_t(head[at + i]);
  return std::int64_t(std::int32_t(v));
}

double big_endian_float32(std::string_view head, std::size_t at) {
  const auto bits = std::uint32_t(big_endian_int32(head, at));
  float value = 0;
  std::memcpy(&value, &bits, sizeof value);
  return double(value);
}

// The first bytes of a file for a message: printable ASCII as is, others as \xNN.
std::string shown(std::string_view head) {
  std::string out;
  for (std::size_t i = 0; i < head.size() && i < 4; ++i) {
    const auto c = std::uint8_t(head[i]);
    if (std::isprint(c)) {
      out += char(c);
    } else {
      static const char* hex = "0123456789abcdef";
      out += cat("\\x", hex[c >> 4], hex[c & 15]);
    }
  }
  return out;
}

}  // namespace

bool has_genesis_magic(std::string_view head) {
  return head.size() >= 4 && head.substr(0, 4) == "IMGF";
}

GenesisHeader parse_genesis_header(const std::string& path, std::string_view head,
                                   std::uint64_t file_size) {
  if (!has_genesis_magic(head))
    throw InputError(cat(path, ": not a GE Genesis image: starts with \"", shown(head),
                         "\", not the magic \"IMGF\" (raw.header \"genesis\")"));
  if (head.size() < kGenesisFixedBytes)
    throw InputError(cat(path, ": GE Genesis header truncated: ", head.size(),
                         " bytes, the fixed "
                         "part alone is ",
                         kGenesisFixedBytes));
  GenesisHeader h;
  h.pixel_offset = big_endian_int32(head, 4);
  h.width = big_endian_int32(head, 8);
  h.height = big_endian_int32(head, 12);
  h.bits = big_endian_int32(head, 16);
  h.compression = big_endian_int32(head, 20);
  auto field = [&](const char* name, int at, std::int64_t value, const std::string& why) {
    return InputError(cat(path, ": GE Genesis header field ", name, " (bytes ", at, "..", at + 3,
                          ") is ", value, ": ", why));
  };
  if (h.pixel_offset < std::int64_t(kGenesisFixedBytes) ||
      std::uint64_t(h.pixel_offset) > file_size)
    throw field("pixel data offset", 4, h.pixel_offset,
                cat("outside the file's ", file_size, " bytes past the fixed header"));
  if (h.width <= 0) throw field("width", 8, h.width, "not positive");
  if (h.height <= 0) throw field("height", 12, h.height, "not positive");
  if (h.bits <= 0) throw field("depth", 16, h.bits, "not positive");
  if (h.compression != 0 && h.compression != 1)
    throw field("compression", 20, h.compression,
                "only 0 (none) and 1 (rectangular) store the samples as they are");
  return h;
}

std::optional<GenesisPixelSize> genesis_pixel_size(std::string_view file,
                                                   const GenesisHeader& header) {
  constexpr std::size_t kImageHeaderAt = 148, kPixelSizeAt = 50;
  if (file.size() < kImageHeaderAt + 4 || header.pixel_offset < std::int64_t(kImageHeaderAt + 4))
    return std::nullopt;
  const std::int64_t image = big_endian_int32(file, kImageHeaderAt);
  if (image < std::int64_t(kImageHeaderAt + 4) ||
      image + std::int64_t(kPixelSizeAt + 8) > header.pixel_offset ||
      std::uint64_t(image) + kPixelSizeAt + 8 > file.size())
    return std::nullopt;
  GenesisPixelSize size;
  size.image_header_offset = image;
  size.x_mm = big_endian_float32(file, std::size_t(image) + kPixelSizeAt);
  size.y_mm = big_endian_float32(file, std::size_t(image) + kPixelSizeAt + 4);
  auto usable = [](double v) { return std::isfinite(v) && v > 0; };
  if (!usable(size.x_mm) || !usable(size.y_mm)) return std::nullopt;
  return size;
}

void check_genesis_pixel_size(const std::string& path, std::string_view file,
                              const GenesisHeader& header,
                              const std::array<double, 2>& configured_mm) {
  const std::optional<GenesisPixelSize> size = genesis_pixel_size(file, header);
  if (!size) return;
  auto off = [](double recorded, double configured) {
    return std::abs(recorded - configured) > 0.01 * configured;
  };
  if (!off(size->x_mm, configured_mm[0]) && !off(size->y_mm, configured_mm[1])) return;
  throw InputError(cat(path, ": GE Genesis image header (at byte ", size->image_header_offset,
                       ") records pixels of ", size->x_mm, " x ", size->y_mm,
                       " mm, the config's ct.pixel_spacing_mm is [", configured_mm[0], ", ",
                       configured_mm[1], "]"));
}

}  // namespace vispack::pipeline

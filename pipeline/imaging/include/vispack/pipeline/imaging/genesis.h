// The fixed part of a GE Genesis (Signa 5.x) image header, the format of the NLM Visible Human
// male's CT files (c_vm<n>.fre): what a raw slice reader needs to find the pixels
// (config raw.header "genesis", slice_io.h read_slice).
//
// Layout (public descriptions of the format: David Clunie's medical image format FAQ, part 4,
// "Signa 5.X"; the GE readers of VTK and ITK agree): the file starts with the magic "IMGF", then
// five big-endian int32: byte offset of the pixel data (4..7), width (8..11), height (12..15),
// bits per pixel (16..19) and compression (20..23: 0 none, 1 rectangular, 2 packed, 3 compressed,
// 4 compressed and packed). Only 0 and 1 store the width × height samples as they are (big-endian
// 16-bit for CT); the others store rows of varying length or deltas and are refused.
// The image header (its byte offset: the big-endian int32 at bytes 148..151) records the pixel
// size: big-endian float32 x and y in mm at its bytes 50..53 and 54..57 (the same sources).
// Pure functions; thread-safe.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

namespace vispack::pipeline {

// Bytes of the fixed part read here (magic and the five fields).
inline constexpr std::size_t kGenesisFixedBytes = 24;

struct GenesisHeader {
  std::int64_t pixel_offset = 0;  // bytes from the start of the file to the first sample
  std::int64_t width = 0, height = 0;
  std::int64_t bits = 0;         // bits per pixel (16 for CT)
  std::int64_t compression = 0;  // 0 none, 1 rectangular: the samples as they are
};

// True when `head` (a file's first bytes) starts with the magic "IMGF".
bool has_genesis_magic(std::string_view head);

// Parses the fixed part from `head`, the file's first bytes (at least kGenesisFixedBytes, else
// "header truncated"), of a file of `file_size` bytes. Throws InputError naming `path` and the
// field at fault: no magic (naming the first bytes found), the header cut short, a pixel offset
// inside the fixed part or beyond the file, a width, height or bit depth that is not positive,
// a compression other than 0 or 1.
GenesisHeader parse_genesis_header(const std::string& path, std::string_view head,
                                   std::uint64_t file_size);

// The pixel size (mm) the image header records, read from `file` (the whole file, or at least
// its header up to the pixel data); none when the file has no image header before its pixels (the
// offset at 148..151 is 0, points inside the fixed part or past the pixel data offset) or records
// no positive finite size there. Never throws.
struct GenesisPixelSize {
  double x_mm = 0, y_mm = 0;
  std::int64_t image_header_offset = 0;
};
std::optional<GenesisPixelSize> genesis_pixel_size(std::string_view file,
                                                   const GenesisHeader& header);

// Throws InputError naming `path`, both sizes and the key `ct.pixel_spacing_mm` when the file's
// recorded pixel size (genesis_pixel_size) differs from `configured_mm` (x, y) by more than 1 % on
// either axis: a clear mismatch (another field of view, the wrong template). Does nothing when the
// file records none.
void check_genesis_pixel_size(const std::string& path, std::string_view file,
                              const GenesisHeader& header,
                              const std::array<double, 2>& configured_mm);

}  // namespace vispack::pipeline

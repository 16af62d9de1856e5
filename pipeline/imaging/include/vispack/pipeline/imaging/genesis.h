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
// Pure functions; thread-safe.
#pragma once

#include <cstdint>
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

}  // namespace vispack::pipeline

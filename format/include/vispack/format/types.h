// Types shared by the packed-volume writer and reader (format/SPEC.md is the byte-level truth).
//
// A packed file (".vpk") holds one volume on a voxel grid: several channels (rgba, ct, labels),
// each cut into cubic bricks of `brick_edge` voxels per side, at every level of a mip pyramid.
// Coordinates follow docs/ARCHITECTURE.md: x = image column, y = image row (downwards),
// z = slice index; voxel (x, y, z) of level 0 has its centre at origin_mm + (x, y, z) * spacing_mm.
// Memory order of every buffer in this API: x fastest, then y, then z; the components of a
// multi-component voxel (rgba) are interleaved. All multi-byte values are little-endian.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "vispack/common/error.h"

namespace vispack::format {

// Format version written by this library. A reader refuses a file whose major is newer;
// a newer minor is read (minor bumps only add optional metadata keys or flag bits that an
// older reader may ignore; see SPEC.md "Versioning").
inline constexpr std::uint16_t kFormatMajor = 1;
inline constexpr std::uint16_t kFormatMinor = 0;
// Brick payloads start at multiples of this many bytes (a page), so a raw brick can be used
// straight from the memory map.
inline constexpr std::uint64_t kPayloadAlignment = 4096;

// Voxel type of a channel.
//   kRgba8  : 4 x uint8 (r, g, b, alpha = body coverage 0..255)
//   kInt16  : int16 (CT in Hounsfield units)
//   kUint8  : uint8 label IDs (0 = unlabelled)
//   kUint16 : uint16 label IDs (0 = unlabelled)
enum class ChannelType : std::uint8_t { kRgba8 = 0, kInt16 = 1, kUint8 = 2, kUint16 = 3 };

// Bytes per voxel of a channel type (4, 2, 1, 2). Throws std::invalid_argument on a bad value.
std::size_t channel_type_bytes(ChannelType type);
// Components per voxel (4 for kRgba8, else 1).
int channel_type_components(ChannelType type);
// "rgba8", "int16", "uint8", "uint16" (the names used in the metadata JSON).
const char* channel_type_name(ChannelType type);
// Inverse of channel_type_name; throws FormatError naming the unknown string.
ChannelType channel_type_from_name(const std::string& name);
// True for the label types (kUint8, kUint16): downsampled by majority, label sets per brick.
inline bool is_label_type(ChannelType type) {
  return type == ChannelType::kUint8 || type == ChannelType::kUint16;
}

// One row of the label table: an ID (> 0), a structure name and its display colour (sRGB).
struct LabelEntry {
  std::uint32_t id = 0;
  std::string name;
  std::array<std::uint8_t, 3> colour{0, 0, 0};
};

// A channel: its name ("rgba", "ct", "labels" by convention) and voxel type.
struct ChannelSpec {
  std::string name;
  ChannelType type = ChannelType::kUint8;
};

// How a brick's payload is stored (SPEC.md "Codecs").
enum class Codec : std::uint8_t {
  kUniform = 0,  // every voxel equals BrickInfo::uniform; no payload bytes at all
  kRaw = 1,      // brick_edge^3 voxels, uncompressed (zero-copy from the memory map)
  kZstd = 2,     // one zstd frame that decodes to brick_edge^3 voxels
};
const char* codec_name(Codec codec);

// One entry of the brick index, as the reader exposes it (validated against the file).
// A brick covers voxels [b * edge, min((b + 1) * edge, level dims)) on each axis; its payload
// always holds edge^3 voxels, the part outside the level being filled by replicating the last
// valid voxel on each axis ("clamp to edge"), so a GPU sampler that clamps sees the same data.
struct BrickInfo {
  int level = 0;
  int channel = 0;                             // index into the channel list
  std::array<std::int64_t, 3> brick{0, 0, 0};  // brick coordinates bx, by, bz in the level's grid
  Codec codec = Codec::kUniform;
  std::uint64_t offset = 0;       // payload offset in the file (0 for uniform bricks)
  std::uint64_t stored_size = 0;  // payload bytes in the file (0 for uniform bricks)
  std::uint64_t checksum = 0;     // xxHash64 (seed 0) of the stored payload (0 if uniform)
  // Per-component minimum and maximum over the brick's valid voxels (not the replicated
  // padding). Scalar channels use element 0 only (the others are 0); int16 is sign-extended.
  std::array<std::int64_t, 4> min{0, 0, 0, 0};
  std::array<std::int64_t, 4> max{0, 0, 0, 0};
  // The voxel value of a uniform brick, as stored bytes (first channel_type_bytes bytes).
  std::array<std::uint8_t, 4> uniform{0, 0, 0, 0};
  // Label channels: the sorted distinct IDs present in the brick's valid voxels, as a range
  // into Reader::label_ids() (label_count == 0 for other channels).
  std::uint32_t label_first = 0;
  std::uint32_t label_count = 0;
};

}  // namespace vispack::format

// On-disk structures of the packed format, version 1 (format/SPEC.md is the prose truth).
// Internal to the format library: every struct's size and field offsets are asserted, and the
// code assumes a little-endian host (as the file is little-endian).
#pragma once

#include <cstddef>
#include <cstdint>

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "vispack_format assumes a little-endian host"
#endif

namespace vispack::format::detail {

// "\x89VPK\r\n\x1a\n": a non-ASCII first byte, then a line ending pair and EOF character, so
// text-mode transfers and truncated downloads are detected as with PNG.
inline constexpr std::uint8_t kMagic[8] = {0x89, 'V', 'P', 'K', '\r', '\n', 0x1A, '\n'};
inline constexpr std::uint32_t kHeaderSize = 128;
inline constexpr std::uint32_t kIndexEntrySize = 64;
inline constexpr std::uint64_t kChecksumFieldOffset = 120;

struct FileHeader {
  std::uint8_t magic[8];
  std::uint16_t version_major;
  std::uint16_t version_minor;
  std::uint32_t header_size;       // 128
  std::uint64_t file_size;         // total bytes of the file
  std::uint64_t payload_offset;    // 4096: first byte of the payload area
  std::uint64_t payload_end;       // end of the payload area (multiple of 4096)
  std::uint64_t metadata_offset;   // == payload_end
  std::uint64_t metadata_size;     // bytes of UTF-8 JSON
  std::uint64_t index_offset;      // metadata end rounded up to 8
  std::uint64_t index_count;       // entries of 64 bytes
  std::uint64_t labels_offset;     // == index end
  std::uint64_t labels_count;      // uint32 label IDs; the file ends right after them
  std::uint32_t index_entry_size;  // 64
  std::uint32_t brick_edge;
  std::uint32_t level_count;
  std::uint32_t channel_count;
  std::uint32_t flags;           // 0 in version 1.0
  std::uint32_t reserved0;       // 0
  std::uint64_t reserved1;       // 0
  std::uint64_t table_checksum;  // xxh64(header[0,120) || metadata || index || labels)
};
static_assert(sizeof(FileHeader) == kHeaderSize, "FileHeader must be 128 bytes");
static_assert(offsetof(FileHeader, file_size) == 16);
static_assert(offsetof(FileHeader, index_entry_size) == 88);
static_assert(offsetof(FileHeader, table_checksum) == kChecksumFieldOffset);

struct IndexEntry {
  std::uint32_t bx, by, bz;
  std::uint8_t level;
  std::uint8_t channel;
  std::uint8_t codec;
  std::uint8_t reserved;  // 0
  std::uint64_t offset;
  std::uint64_t stored_size;
  std::uint64_t checksum;
  std::uint8_t min[8];  // voxel bytes of the per-component minimum, rest 0
  std::uint8_t max[8];
  std::uint32_t label_first;
  std::uint32_t label_count;
};
static_assert(sizeof(IndexEntry) == kIndexEntrySize, "IndexEntry must be 64 bytes");
static_assert(offsetof(IndexEntry, offset) == 16);
static_assert(offsetof(IndexEntry, min) == 40);
static_assert(offsetof(IndexEntry, label_first) == 56);

inline constexpr std::uint64_t align_up(std::uint64_t value, std::uint64_t alignment) {
  return (value + alignment - 1) / alignment * alignment;
}

}  // namespace vispack::format::detail

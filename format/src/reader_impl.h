// Reader::Impl, the state of one open Reader (private to the format reader): declared here,
// defined by concern: the header and metadata (reader_header.cpp), the brick index
// (reader_index.cpp), payload I/O, decoding and regions (reader_payload.cpp), the file check
// (reader_check.cpp). Thread-safety as Reader's: after open() every const member may be called
// from many threads (the zstd contexts are pooled under dctx_mutex).
#pragma once

#include <sys/mman.h>
#include <unistd.h>
#include <zstd.h>

#include <array>
#include <cstdint>
#include <cstring>
#include <limits>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "int_math.h"
#include "layout.h"
#include "vispack/common/error.h"
#include "vispack/format/geometry.h"
#include "vispack/format/reader.h"

namespace vispack::format {
namespace detail {

inline std::string brick_name(const std::vector<ChannelSpec>& channels, int level, int channel,
                              std::int64_t bx, std::int64_t by, std::int64_t bz) {
  std::string name =
      channel >= 0 && channel < int(channels.size()) ? channels[channel].name : cat("#", channel);
  return cat("level ", level, " channel ", name, " brick (", bx, ",", by, ",", bz, ")");
}

// Decodes the voxel bytes of a min/max field into per-component integers.
inline std::array<std::int64_t, 4> decode_value(ChannelType type, const std::uint8_t* bytes) {
  std::array<std::int64_t, 4> out{0, 0, 0, 0};
  switch (type) {
    case ChannelType::kRgba8:
      for (int c = 0; c < 4; ++c)
        out[c] = bytes[c];
      break;
    case ChannelType::kInt16: {
      std::int16_t v;
      std::memcpy(&v, bytes, 2);
      out[0] = v;
      break;
    }
    case ChannelType::kUint8:
      out[0] = bytes[0];
      break;
    case ChannelType::kUint16: {
      std::uint16_t v;
      std::memcpy(&v, bytes, 2);
      out[0] = v;
      break;
    }
  }
  return out;
}

}  // namespace detail

using detail::align_up;
using detail::brick_name;
using detail::decode_value;
using detail::FileHeader;
using detail::IndexEntry;
using nlohmann::json;

struct Reader::Impl {
  std::string path;
  int fd = -1;
  const std::uint8_t* base = nullptr;
  std::size_t size = 0;
  FileHeader header{};
  json meta;
  int edge = 0;
  VolumeGeometry geometry;
  const std::vector<LevelInfo>& levels = geometry.levels;
  std::vector<ChannelSpec> channels;
  std::vector<LabelEntry> label_table;
  std::vector<BrickInfo> bricks;
  std::vector<std::uint32_t> label_ids;
  mutable std::mutex dctx_mutex;
  mutable std::vector<ZSTD_DCtx*> dctx_free;

  ~Impl() {
    for (ZSTD_DCtx* d : dctx_free)
      ZSTD_freeDCtx(d);
    if (base) ::munmap(const_cast<std::uint8_t*>(base), size);
    if (fd >= 0) ::close(fd);
  }

  [[noreturn]] void fail(DefectKind kind, const std::string& what) const {
    Finding f;
    f.kind = kind;
    f.detail = what;
    throw FileDefect(path, std::move(f));
  }
  [[noreturn]] void fail_brick(DefectKind kind, int level, int channel, std::int64_t bx,
                               std::int64_t by, std::int64_t bz, const std::string& what) const {
    throw FileDefect(path, finding(kind, level, channel, {bx, by, bz}, what));
  }
  [[noreturn]] void fail_brick(DefectKind kind, const BrickInfo& b, const std::string& what) const {
    fail_brick(kind, b.level, b.channel, b.brick[0], b.brick[1], b.brick[2], what);
  }
  Finding finding(DefectKind kind, int level, int channel, const std::array<std::int64_t, 3>& at,
                  const std::string& what) const {
    Finding f;
    f.kind = kind;
    f.has_brick = true;
    f.level = level;
    f.channel = channel;
    f.channel_name = channel >= 0 && channel < int(channels.size())
                         ? channels[std::size_t(channel)].name
                         : cat("#", channel);
    f.brick = at;
    f.detail = what;
    return f;
  }

  std::string name(const BrickInfo& b) const {
    return brick_name(channels, b.level, b.channel, b.brick[0], b.brick[1], b.brick[2]);
  }

  std::size_t brick_bytes(int channel) const {
    return std::size_t(edge) * std::size_t(edge) * std::size_t(edge) *
           channel_type_bytes(channels[std::size_t(channel)].type);
  }

  void map();

  // The 128-byte header (SPEC.md "Header"), checked field by field before any offset in it is
  // used: what the file is, the fixed fields, where the blocks lie, the table checksum.
  void parse_header(const ReaderLimits& limits);

  // Magic, version and file size: is this a packed volume this reader can read, and whole.
  void check_identity() const;

  // The fields with fixed or bounded values: sizes, reserved fields, brick edge, counts.
  void check_header_fields() const;

  // Payloads, metadata, index and label IDs lie one after the other, inside the file, in that
  // order, with the limits' sizes.
  void check_block_layout(const ReaderLimits& limits) const;

  // xxHash64 of header[0, 120) and everything from the metadata to the end of the file.
  void check_table_checksum() const;

  void parse_metadata(const ReaderLimits& limits);

  // A payload's byte range and its brick (for the overlap check).
  struct PayloadSpan {
    std::uint64_t offset, end;
    std::size_t k;
  };

  // The brick index (SPEC.md "Brick index"): one entry per brick in level, channel, z, y, x
  // order, each checked (parse_entry) before it is used, then the payloads' layout.
  void parse_index();

  // Index entry k, expected to describe brick `at` of level l, channel c: read into bricks[k],
  // its payload's range appended to `spans`. Throws FileDefect naming the brick.
  void parse_entry(std::size_t k, int l, int c, const std::array<std::int64_t, 3>& at,
                   std::vector<PayloadSpan>& spans);

  // The codec and its payload: a uniform brick has none; a raw one is exactly `raw_bytes`, a
  // zstd one smaller; both aligned and inside the payload area. Sets b.codec.
  template <typename Bad>
  void check_entry_codec(const IndexEntry& e, BrickInfo& b, std::uint64_t raw_bytes,
                         const Bad& bad) const;

  // A label channel's brick names a non-empty, strictly ascending run of the file's label IDs
  // that matches its min and max; any other channel's brick names none.
  template <typename Bad>
  void check_entry_labels(const IndexEntry& e, const BrickInfo& b, ChannelType type,
                          const Bad& bad) const;

  // Payloads do not overlap, and the last one's aligned end is payload_end.
  void check_payload_spans(std::vector<PayloadSpan>& spans) const;

  // Reader::check's parts (defined after the Reader's members).
  std::optional<Finding> check_brick(const BrickInfo& b, bool deep) const;
  std::optional<Finding> check_decoded(const BrickInfo& b,
                                       const std::vector<std::uint8_t>& buf) const;
  void check_padding(std::vector<Finding>& findings) const;

  ZSTD_DCtx* acquire() const;
  void release(ZSTD_DCtx* d) const;

  void decode(const BrickInfo& b, void* out, std::size_t out_size, bool verify_checksum) const;

  // Level `level`'s geometry; std::out_of_range naming the file unless level and channel exist.
  const LevelInfo& checked_level(int level, int channel) const;

  const BrickInfo& brick(int channel, int level, std::int64_t bx, std::int64_t by,
                         std::int64_t bz) const;

  // Copies the part of brick `b` inside the box into `out` (the box's buffer). `tmp` is a
  // scratch buffer of brick_bytes used for zstd bricks.
  void copy_brick(const BrickInfo& b, const std::array<std::int64_t, 3>& o,
                  const std::array<std::int64_t, 3>& n, std::uint8_t* out,
                  std::vector<std::uint8_t>& tmp) const;

  void region(int channel, int level, const std::array<std::int64_t, 3>& o,
              const std::array<std::int64_t, 3>& n, void* out, int threads) const;
};

}  // namespace vispack::format

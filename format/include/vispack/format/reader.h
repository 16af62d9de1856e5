// Memory-mapped reader of packed volume files (format/SPEC.md).
//
// Reader::open maps the file read-only and validates, before trusting any of it: the magic and
// version, every header offset and size against the file size, the table checksum (header +
// metadata + index + label IDs), the metadata JSON (types and ranges of every key it uses),
// and every index entry (position, codec, alignment, bounds, no overlap, label-set range).
// A file that fails any check is refused with a FileDefect (a FormatError naming the file and
// the field or brick, carrying a numbered Finding, findings.h); nothing is read out of bounds.
// ReaderLimits bounds what a header may ask for, so a hostile header is refused by a check rather
// than by running out of memory.
//
// Brick payload checksums are not checked on every read (that would cost a full hash per
// decode); check() / verify() check them all, or pass verify_checksum = true to decode_brick.
// Part of vispack_format_reader (links the format core, zstd, xxHash; never the writer).
//
// Thread-safety: after open(), every const member function may be called from several threads
// at once (the viewer decodes bricks on worker threads). A Reader is movable, not copyable;
// views and BrickInfo references stay valid while the Reader lives.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "vispack/format/findings.h"
#include "vispack/format/geometry.h"
#include "vispack/format/limits.h"
#include "vispack/format/types.h"

namespace vispack::format {

// A read-only view of bytes inside the memory map.
struct ByteView {
  const std::uint8_t* data = nullptr;
  std::size_t size = 0;
};

// Result of Reader::verify(): ok, or the first problem found (in file order of the checks:
// payload checksums in index order, then padding) with the brick it concerns.
struct VerifyResult {
  bool ok = true;
  std::string message;             // one line naming the brick or the byte range at fault
  std::optional<BrickInfo> brick;  // the bad brick (level, channel, brick x/y/z), if any
};

class Reader {
 public:
  // Maps and validates `path`. Throws IoError (cannot open/stat/map) or FormatError (any
  // check above fails; the message names the file and the field or brick).
  static Reader open(const std::string& path, const ReaderLimits& limits = {});

  ~Reader();
  Reader(Reader&&) noexcept;
  Reader& operator=(Reader&&) noexcept;
  Reader(const Reader&) = delete;
  Reader& operator=(const Reader&) = delete;

  const std::string& path() const;
  std::uint64_t file_size() const;
  std::uint16_t version_major() const;
  std::uint16_t version_minor() const;
  // The whole metadata JSON block (SPEC.md "Metadata"); "extra" holds the writer's extras.
  const nlohmann::json& metadata() const;

  int brick_edge() const;
  int level_count() const;
  // Throws std::out_of_range for a level outside [0, level_count()).
  const LevelInfo& level(int level) const;
  std::array<std::int64_t, 3> dims(int level = 0) const { return this->level(level).dims; }
  std::array<std::int64_t, 3> brick_grid(int level) const { return this->level(level).bricks; }
  std::array<double, 3> spacing_mm(int level = 0) const { return this->level(level).spacing_mm; }
  std::array<double, 3> origin_mm(int level = 0) const { return this->level(level).origin_mm; }

  // Stored channels (label channels with their stored type, uint8 or uint16).
  const std::vector<ChannelSpec>& channels() const;
  // Index of the channel called `name`, or nullopt.
  std::optional<int> find_channel(const std::string& name) const;
  // Same, but throws std::out_of_range naming the channel and the file when absent.
  int channel_index(const std::string& name) const;
  const std::vector<LabelEntry>& label_table() const;

  // Bytes of one decoded brick of `channel`: brick_edge^3 * channel_type_bytes.
  std::size_t brick_bytes(int channel) const;
  // The index entry of one brick. Throws std::out_of_range for a bad channel/level/brick.
  const BrickInfo& brick(int channel, int level, std::int64_t bx, std::int64_t by,
                         std::int64_t bz) const;
  // Every index entry, in index order (level, channel, bz, by, bx).
  const std::vector<BrickInfo>& bricks() const;
  // All label-set IDs of the file; a brick's set is [label_first, label_first + label_count).
  const std::vector<std::uint32_t>& label_ids() const;
  // The label IDs present in one brick (a copy, sorted ascending).
  std::vector<std::uint32_t> brick_labels(const BrickInfo& brick) const;

  // Zero-copy view of a raw-codec brick's payload inside the map (brick_bytes(channel) bytes,
  // 4096-aligned), or nullopt for uniform and zstd bricks.
  std::optional<ByteView> raw_brick_view(const BrickInfo& brick) const;
  // The stored payload bytes of any brick (empty view for uniform bricks).
  ByteView payload(const BrickInfo& brick) const;
  // Lets the kernel drop this process's mapping of the brick's payload pages (madvise
  // MADV_DONTNEED; the pages stay in the page cache and a later read maps them again). For a
  // reader that streams every brick once (the OME-Zarr export): its resident memory then stays
  // at the bricks in flight, not the file's size. Views of the payload stay valid (they read
  // the pages back). No effect on uniform bricks.
  void release_payload_pages(const BrickInfo& brick) const;

  // Decodes one brick into `out` (at least brick_bytes(channel) bytes): edge^3 voxels, x
  // fastest, padding replicated from the last valid voxel on each axis. With verify_checksum
  // the payload's xxHash64 is checked first. Throws FormatError naming the file and brick if
  // the payload does not decode to exactly brick_bytes bytes or the checksum differs (a
  // FileDefect of kind kPayloadDecode or kPayloadChecksum);
  // std::invalid_argument if out_size is too small.
  void decode_brick(const BrickInfo& brick, void* out, std::size_t out_size,
                    bool verify_checksum = false) const;

  // Copies the box [x0, x0 + nx) x [y0, y0 + ny) x [z0, z0 + nz) of `channel` at `level` into
  // `out` (nx * ny * nz voxels, x fastest). The box must lie inside the level
  // (std::out_of_range otherwise). Throws FormatError if a brick does not decode.
  void read_region(int channel, int level, std::int64_t x0, std::int64_t y0, std::int64_t z0,
                   std::int64_t nx, std::int64_t ny, std::int64_t nz, void* out) const;
  void read_region(const std::string& channel, int level, std::int64_t x0, std::int64_t y0,
                   std::int64_t z0, std::int64_t nx, std::int64_t ny, std::int64_t nz,
                   void* out) const {
    read_region(channel_index(channel), level, x0, y0, z0, nx, ny, nz, out);
  }
  // A whole level of one channel (dims product * channel_type_bytes bytes). Bricks are decoded
  // on `threads` threads (0 = resolve_threads()).
  std::vector<std::uint8_t> read_level(int channel, int level, int threads = 0) const;
  std::vector<std::uint8_t> read_level(const std::string& channel, int level,
                                       int threads = 0) const {
    return read_level(channel_index(channel), level, threads);
  }

  // Checks every brick payload's checksum (and, with `deep`, that it decodes and that its
  // min/max/label set match the index) and that every byte not covered by the header, the
  // metadata, the index, the label IDs or a payload is zero. Returns every finding (kinds
  // 8..12 of findings.h): at most one per brick (its first problem), in index order, then one
  // per padding run holding a non-zero byte, in file order. Empty: the file is sound.
  // Bricks are checked on `threads` threads (0 = resolve_threads()).
  std::vector<Finding> check(bool deep = false, int threads = 0) const;
  // The first finding of check() as a VerifyResult (ok when there is none).
  VerifyResult verify(bool deep = false, int threads = 0) const;

 private:
  struct Impl;
  explicit Reader(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace vispack::format

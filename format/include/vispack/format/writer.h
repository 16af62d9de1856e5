// Streaming writer of packed volume files (format/SPEC.md).
//
// Usage:
//   vispack::format::WriterOptions options;
//   options.dims = {nx, ny, nz};
//   options.spacing_mm = {0.33, 0.33, 1.0};
//   options.channels = {{"rgba", ChannelType::kRgba8}, {"ct", ChannelType::kInt16},
//                       {"labels", ChannelType::kUint16}};
//   options.label_table = {{1, "skin", {230, 180, 150}}, ...};
//   vispack::format::Writer writer("out/volume.vpk", options);
//   for (z ...) writer.append_slice({rgba_slice, ct_slice, label_slice});
//   writer.finish();  // the file appears complete at "out/volume.vpk", or not at all
//
// Memory, whatever nz is: one level-0 brick row (dims[0] x dims[1] x brick_edge voxels of every
// stored channel: the slab being filled; nothing else of that size; its pages that have only
// ever received zeros, most of the colour and labels outside the body, stay untouched and take
// no memory), plus one slice of each coarser level and two per level being reduced, one band of
// bricks (one brick row along y of one channel of a coarser level) read back to be encoded, a
// few compressed bricks (each is written as soon as it and the bricks before it are made) and
// one brick of scratch per thread.
// The coarser levels' partly filled slabs (a third of a level-0 row at most, raw) are kept as
// zstd-compressed strips (one per band of bricks of a slice: outside the body they shrink to
// almost nothing), in memory up to WriterOptions::coarse_levels_memory_bytes, the rest in a
// nameless temporary file beside the output (page cache, not the resident set).
// Threads: `threads` threads, the calling thread included (threads − 1 persistent workers,
// started by the constructor and joined by finish() or the destructor; none for one thread).
// They share each slice's copy into the slab and its coarser levels' strips, and when a slab is
// full they make its bricks, the calling thread too; append_slice returns once they are written:
// the slab buffer is then refilled (the price of holding one row: reading the next slices does
// not overlap the compression of this slab).
// Determinism: the same slices and options give a byte-identical file, whatever `threads`
// (no timestamps; slabs are written in the order they fill, bricks in index order within).
// Thread-safety: a Writer is used from one thread at a time.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "vispack/format/types.h"

typedef struct ZSTD_CCtx_s ZSTD_CCtx;
typedef struct ZSTD_DCtx_s ZSTD_DCtx;

namespace vispack {
class ZeroPagedBuffer;
}

namespace vispack::format {

struct WriterOptions {
  std::array<std::int64_t, 3> dims{0, 0, 0};  // x, y, z voxels of level 0; each in [1, 2^31 - 1]
  std::array<double, 3> spacing_mm{1, 1, 1};  // voxel spacing of level 0 (> 0, finite)
  std::array<double, 3> origin_mm{0, 0, 0};   // centre of voxel (0, 0, 0)
  int brick_edge = 64;                        // power of two in [4, 1024]
  int zstd_level = 3;                         // 1..22 (negative: zstd's fast levels)
  bool compress = true;                       // false: every non-uniform brick stored raw
  int threads = 0;                            // compression threads; 0 = resolve_threads()
  std::vector<ChannelSpec> channels;          // 1..16 channels with distinct, non-empty names
  // For a label channel. The stored type of every label channel is chosen here: uint8 when
  // the table's largest ID is <= 255, else uint16 (with an empty table, the ChannelSpec type).
  std::vector<LabelEntry> label_table;
  // Free-form JSON object stored under the metadata key "extra": provenance (tool version,
  // config hash, input hashes), missing/duplicated slices, registration quality... It must not
  // contain anything that changes between runs if the output is to be byte-reproducible.
  nlohmann::json extra_metadata = nlohmann::json::object();
  // The coarser levels' partly filled slabs (about a third of a level-0 brick row, raw; kept
  // compressed) stay in memory up to this many bytes of compressed strips, the rest goes to a
  // nameless temporary file beside the output (page cache, not resident memory). The file is the
  // same either way. At 2048x1216 the strips take 39 MB per 128 slices of a stack cleared
  // outside the body (~50 MB once every level is partly filled): the default keeps the pack's
  // peak within one brick row + 300 MB with room to spare.
  std::uint64_t coarse_levels_memory_bytes = std::uint64_t(16) << 20;
};

// One level-0 brick encoded exactly as the Writer stores it (SPEC.md "Codecs"): what a shard of a
// sharded pack hands to the merge (encode_level0_slab, Writer::provide_level0_slab).
struct EncodedBrick {
  Codec codec = Codec::kUniform;
  std::array<std::uint8_t, 8> min{};  // the index entry's min / max bytes (SPEC.md "Brick index")
  std::array<std::uint8_t, 8> max{};
  std::uint64_t checksum = 0;         // xxh64(payload); 0 for a uniform brick
  std::vector<std::uint8_t> payload;  // stored bytes; empty for a uniform brick, or when in a file
  std::vector<std::uint32_t> labels;  // label channels: the brick's ID set, ascending; else empty
  // Or the stored bytes lie in a file (Writer::provide_level0_slab with a PayloadFile, `payload`
  // empty): `file_bytes` bytes at `file_offset` of it; 0 bytes for a uniform brick.
  std::uint64_t file_offset = 0;
  std::uint64_t file_bytes = 0;
};

// An open file that provided bricks' stored bytes are copied from (EncodedBrick::file_offset):
// the Writer copies them into its output (copy_file_range, else read and write) when it writes
// their slab, and never holds them in memory. Owned by the caller, who keeps `fd` open and the
// bytes unchanged until then (the slab's last level-1 slice appended, or finish()); `name` names
// it in errors.
struct PayloadFile {
  int fd = -1;
  std::string name;
};

// The stored channel list `options` give (label channels narrowed as the Writer narrows them).
std::vector<ChannelSpec> stored_channels_for(const WriterOptions& options);

// Number of level-0 slabs (brick rows along z): ceil(dims[2] / brick_edge).
std::int64_t level0_slab_count(const WriterOptions& options);

// How encode_level0_slab receives label channels: in append_slice's convention (uint16), or
// already in their stored type (stored_channels_for: uint8 when the label table's IDs fit it).
enum class SlabLabels { kUint16, kStored };

// Encodes the level-0 bricks of slab `bz` (slices [bz * E, min((bz + 1) * E, dims[2]))) as a
// Writer with the same options stores them: byte-identical payloads, min, max, checksums and
// label sets, whatever `options.threads`. `channel_slabs[c]` holds the slab's slices of channel c
// one after the other, in append_slice's convention, labels as `labels` says (kStored spares the
// narrowed copy of a uint16 slab: its IDs are then not checked). Returns the bricks in index
// order within the slab: channel, then by, then bx (bx fastest).
// With `level1` non-null, also gives the slab's level-1 slices as the Writer reduces them: per
// stored channel, ceil(nzv / 2) slices of ceil(dims[0] / 2) x ceil(dims[1] / 2) voxels of the
// stored type, one after the other (what Writer::append_level1_slice takes); empty vectors when
// the volume has a single level.
// Throws std::invalid_argument (bad options, bz out of range, wrong pointer count), InputError
// (a label ID does not fit the stored type).
std::vector<EncodedBrick> encode_level0_slab(
    const WriterOptions& options, std::int64_t bz, const std::vector<const void*>& channel_slabs,
    std::vector<std::vector<std::uint8_t>>* level1 = nullptr,
    SlabLabels labels = SlabLabels::kUint16);

// Receives the level-1 slices of a slab one at a time: slice `k` of stored channel `channel`,
// `bytes` bytes (ceil(dims[0] / 2) x ceil(dims[1] / 2) voxels of the stored type), every slice of
// channel 0 in order, then channel 1's, ... The bytes are valid during the call only.
using Level1SliceSink =
    std::function<void(std::size_t channel, int k, const std::uint8_t* slice, std::size_t bytes)>;

// encode_level0_slab with the level-1 slices handed to `level1` (when set and the volume has a
// level 1) as they are reduced, none held, and with `zero_pages`: per channel, the buffer its
// slab lies in (ZeroPagedBuffer) or null; bytes in pages it knows to be zero are taken as zeros
// without being read, so those pages are never faulted in (the same bytes result).
std::vector<EncodedBrick> encode_level0_slab(const WriterOptions& options, std::int64_t bz,
                                             const std::vector<const void*>& channel_slabs,
                                             const Level1SliceSink& level1, SlabLabels labels,
                                             const std::vector<const ZeroPagedBuffer*>& zero_pages);

// Decodes `brick` into brick_edge^3 voxels of `stored` type at `out` (brick_edge^3 *
// channel_type_bytes(stored) bytes): the merge of a sharded pack rebuilds level 0 from it to
// compute the coarser levels. Throws FormatError naming `what` when the payload does not match
// its checksum or does not decode to exactly that size.
void decode_encoded_brick(const EncodedBrick& brick, ChannelType stored, int brick_edge,
                          std::uint8_t* out, const std::string& what);

// One zstd frame of `size` bytes at `level` (the level-1 slices a sharded pack's slab file
// carries), and its inverse, which throws FormatError naming `what` unless the frame decodes to
// exactly out_size bytes.
std::vector<std::uint8_t> compress_bytes(const void* data, std::size_t size, int level);
void decompress_bytes(const std::uint8_t* src, std::size_t size, std::uint8_t* out,
                      std::size_t out_size, const std::string& what);

// compress_bytes fed piece by piece: one zstd frame of exactly `size` bytes (its header records
// the size) at `level`, none of its input held; decompress_bytes and ZstdFrameReader read it.
// Not necessarily the bytes compress_bytes gives for the same input. Thread-safety: one thread.
class ZstdFrameWriter {
 public:
  ZstdFrameWriter(std::uint64_t size, int level);
  ~ZstdFrameWriter();
  ZstdFrameWriter(const ZstdFrameWriter&) = delete;
  ZstdFrameWriter& operator=(const ZstdFrameWriter&) = delete;
  // The next n bytes of the frame's content. Throws std::invalid_argument past `size`, Error when
  // zstd fails.
  void write(const void* data, std::size_t n);
  // The frame, once every byte was written (std::invalid_argument before).
  std::vector<std::uint8_t> finish();

 private:
  ZSTD_CCtx* cctx_ = nullptr;
  std::uint64_t left_ = 0;
  std::vector<std::uint8_t> out_;
};

// Decodes one zstd frame `src[0, size)` piece by piece into the caller's buffers (none of the
// decoded content held). Throws FormatError naming `what` when the frame does not decode, ends
// early, or (finish()) holds more bytes or trailing data. Thread-safety: one thread.
class ZstdFrameReader {
 public:
  ZstdFrameReader(const std::uint8_t* src, std::size_t size, std::string what);
  ~ZstdFrameReader();
  ZstdFrameReader(const ZstdFrameReader&) = delete;
  ZstdFrameReader& operator=(const ZstdFrameReader&) = delete;
  // The next n decoded bytes into out.
  void read(std::uint8_t* out, std::size_t n);
  // Checks that the frame ended exactly here.
  void finish();

 private:
  ZSTD_DCtx* dctx_ = nullptr;
  const std::uint8_t* src_;
  std::size_t size_, pos_ = 0;
  std::string what_;
  bool ended_ = false;
};

class Writer {
 public:
  // Validates the options (std::invalid_argument naming the bad field) and creates the
  // temporary file beside `path` (IoError if it cannot).
  Writer(std::string path, WriterOptions options);
  ~Writer();  // without finish(), the temporary file is removed and `path` is left untouched
  Writer(const Writer&) = delete;
  Writer& operator=(const Writer&) = delete;
  Writer(Writer&&) noexcept;
  Writer& operator=(Writer&&) noexcept;

  // Appends the next z slice of every channel, in options.channels order. Each pointer holds
  // dims[0] * dims[1] voxels of that channel's type, x fastest; label channels are always
  // passed as uint16 (the writer narrows them to uint8 when that is the stored type).
  // The pointers are only read during the call.
  // Throws std::invalid_argument (wrong pointer count, null pointer, more than dims[2] slices),
  // InputError (a label ID does not fit the stored type; names slice and voxel), IoError.
  void append_slice(const std::vector<const void*>& channel_slices);

  // Hands over the already encoded level-0 bricks of slab `bz` (encode_level0_slab, possibly
  // run by another process): the Writer stores them as they are instead of encoding that slab.
  // Call it before the slab's last slice is appended; the slab's slices must still be appended
  // (the coarser levels are computed from them), or its level-1 slices (append_level1_slice),
  // and must be the slices the bricks were encoded from, or the file is inconsistent. A volume
  // of a single level (it fits one brick) has no level 1: provide its one slab, then finish().
  // Throws std::invalid_argument (bz out of range, slab already flushed or provided, wrong brick
  // count). With `file`, bricks whose `payload` is empty take their stored bytes from it
  // (EncodedBrick::file_offset / file_bytes; PayloadFile says how long it must stay open): a
  // merge copies level 0 from its shards' files without reading it into memory. Copying throws
  // IoError naming the file when it is shorter than a brick's range.
  void provide_level0_slab(std::int64_t bz, std::vector<EncodedBrick> bricks,
                           const PayloadFile* file = nullptr);

  // For a merge that has level 0 only as encoded bricks: appends the next slice of level 1 (the
  // 2x2x2 reduction of level-0 slices 2k and 2k + 1, or of the last slice alone when dims[2] is
  // odd, by downsample_slice: level1_slices_of_slab gives them), each pointer holding
  // ceil(dims[0] / 2) * ceil(dims[1] / 2) voxels of the channel's STORED type (labels narrowed).
  // Every level-0 slab must be provided (provide_level0_slab) before its first level-1 slice;
  // a Writer fed this way takes no append_slice. slices_written() counts the level-0 slices
  // covered. The file is byte-identical to append_slice of the level-0 slices the bricks and
  // level-1 slices came from. Throws std::invalid_argument (misuse, naming it).
  void append_level1_slice(const std::vector<const void*>& channel_slices);

  // Slices appended so far.
  std::int64_t slices_written() const;

  // Writes the remaining slabs, the pyramid tail, metadata and index, and commits the file
  // atomically. Throws std::invalid_argument if fewer than dims[2] slices were appended;
  // IoError on write failure.
  void finish();

  // The stored channel list (label channels narrowed as described above).
  const std::vector<ChannelSpec>& stored_channels() const;

  // Number of mip levels a volume of `dims` gets with bricks of `brick_edge`: levels are
  // added (each halving every dim, rounding up) until the whole level fits in one brick.
  static int level_count_for(const std::array<std::int64_t, 3>& dims, int brick_edge);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Convenience: writes a whole in-memory volume. `channel_volumes[c]` holds dims product voxels
// of channel c (labels as uint16). Throws like Writer.
void write_volume(const std::string& path, const WriterOptions& options,
                  const std::vector<const void*>& channel_volumes);

}  // namespace vispack::format

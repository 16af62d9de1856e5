// The chunk bytes of an OME-Zarr export (ome_zarr.h), one per brick and image: the stored zstd
// frame itself when it already is the chunk (scalar channels: same layout, x fastest, and a frame
// that names its decoded size), else the brick decoded, its components split out (colour: the
// r, g, b planes one after the other; alpha: component 3) and compressed with zstd. A brick whose
// values equal the image's fill value everywhere (known from the index's min and max, without
// decoding) gives no chunk. Internal to vispack_format_export.
//
// Thread-safety: one ChunkEncoder per thread (it owns a zstd context and buffers); the Reader is
// shared (its const members are thread-safe).
#pragma once

#include <cstdint>
#include <map>
#include <utility>
#include <vector>

#include "ome_zarr_plan.h"
#include "vispack/format/reader.h"

struct ZSTD_CCtx_s;

namespace vispack::format::ome_zarr {

struct EncodedChunk {
  enum class How { kSkipped, kCopied, kEncoded };
  How how = How::kSkipped;
  ByteView copied;                  // kCopied: the brick's payload inside the reader's map
  std::vector<std::uint8_t> bytes;  // kEncoded: one zstd frame
  // The chunk's bytes; size 0 when skipped (`bytes` may hold an earlier chunk's).
  const std::uint8_t* data() const { return how == How::kCopied ? copied.data : bytes.data(); }
  std::size_t size() const {
    return how == How::kSkipped ? 0 : how == How::kCopied ? copied.size : bytes.size();
  }
};

class ChunkEncoder {
 public:
  // `copy_stored` false re-encodes the chunks that could be copied (to measure the copy).
  ChunkEncoder(const Reader& reader, int zstd_level, bool copy_stored);
  ~ChunkEncoder();
  ChunkEncoder(const ChunkEncoder&) = delete;
  ChunkEncoder& operator=(const ChunkEncoder&) = delete;

  // The chunk of `image` for `brick` (a brick of image.channel). Decodes the brick at most once
  // for consecutive calls with the same brick (colour, then alpha). Throws FormatError naming
  // the brick if its payload does not decode.
  void encode(const BrickInfo& brick, const ExportImage& image, EncodedChunk& out);

 private:
  // True when component `c` of the brick is one value everywhere (its min equals its max:
  // the padding replicates valid voxels, so the whole decoded brick holds that value).
  static bool constant(const BrickInfo& brick, int c) { return brick.min[c] == brick.max[c]; }
  const std::vector<std::uint8_t>& decoded(const BrickInfo& brick);
  void compress(const void* data, std::size_t size, EncodedChunk& out);
  void constant_chunk(const ExportImage& image, const std::array<std::int64_t, 3>& values,
                      EncodedChunk& out);

  const Reader& reader_;
  int zstd_level_;
  bool copy_stored_;
  std::size_t voxels_;  // brick_edge^3
  ZSTD_CCtx_s* cctx_ = nullptr;
  std::vector<std::uint8_t> brick_, planes_;
  const BrickInfo* decoded_brick_ = nullptr;
  // Compressed constant chunks, by (image kind and type, component values).
  std::map<std::pair<int, std::array<std::int64_t, 3>>, std::vector<std::uint8_t>> constants_;
};

}  // namespace vispack::format::ome_zarr

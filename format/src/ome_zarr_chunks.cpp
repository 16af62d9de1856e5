#include "ome_zarr_chunks.h"

#include <zstd.h>

#include <cstring>

#include "vispack/common/error.h"

namespace vispack::format::ome_zarr {

ChunkEncoder::ChunkEncoder(const Reader& reader, int zstd_level, bool copy_stored)
    : reader_(reader), zstd_level_(zstd_level), copy_stored_(copy_stored) {
  const std::size_t e = std::size_t(reader.brick_edge());
  voxels_ = e * e * e;
  cctx_ = ZSTD_createCCtx();
  if (cctx_ == nullptr) throw Error("zstd: cannot create a compression context");
}

ChunkEncoder::~ChunkEncoder() {
  ZSTD_freeCCtx(cctx_);
}

const std::vector<std::uint8_t>& ChunkEncoder::decoded(const BrickInfo& brick) {
  if (decoded_brick_ != &brick) {
    brick_.resize(reader_.brick_bytes(brick.channel));
    decoded_brick_ = nullptr;
    reader_.decode_brick(brick, brick_.data(), brick_.size());
    decoded_brick_ = &brick;
  }
  return brick_;
}

void ChunkEncoder::compress(const void* data, std::size_t size, EncodedChunk& out) {
  out.how = EncodedChunk::How::kEncoded;
  out.bytes.resize(ZSTD_compressBound(size));
  const std::size_t n =
      ZSTD_compressCCtx(cctx_, out.bytes.data(), out.bytes.size(), data, size, zstd_level_);
  if (ZSTD_isError(n)) throw Error(cat("zstd: cannot compress a chunk: ", ZSTD_getErrorName(n)));
  out.bytes.resize(n);
}

void ChunkEncoder::constant_chunk(const ExportImage& image,
                                  const std::array<std::int64_t, 3>& values, EncodedChunk& out) {
  const auto key = std::make_pair(int(image.kind) * 16 + int(image.channel_type), values);
  auto it = constants_.find(key);
  if (it == constants_.end()) {
    std::vector<std::uint8_t> chunk(voxels_ * image.item_bytes * std::size_t(image.components));
    for (int c = 0; c < image.components; ++c) {
      std::uint8_t* plane = chunk.data() + std::size_t(c) * voxels_ * image.item_bytes;
      if (image.item_bytes == 1) {
        std::memset(plane, int(values[std::size_t(c)]), voxels_);
      } else {
        const std::uint16_t v = std::uint16_t(values[std::size_t(c)]);  // int16 two's complement
        for (std::size_t i = 0; i < voxels_; ++i)
          std::memcpy(plane + 2 * i, &v, 2);
      }
    }
    compress(chunk.data(), chunk.size(), out);
    it = constants_.emplace(key, out.bytes).first;
  }
  out.how = EncodedChunk::How::kEncoded;
  out.bytes = it->second;
}

void ChunkEncoder::encode(const BrickInfo& brick, const ExportImage& image, EncodedChunk& out) {
  out.how = EncodedChunk::How::kSkipped;
  switch (image.kind) {
    case ImageKind::kColour: {
      if (constant(brick, 0) && constant(brick, 1) && constant(brick, 2)) {
        const std::array<std::int64_t, 3> v{brick.min[0], brick.min[1], brick.min[2]};
        if (v[0] == image.fill_value && v[1] == image.fill_value && v[2] == image.fill_value)
          return;
        constant_chunk(image, v, out);
        return;
      }
      const std::vector<std::uint8_t>& rgba = decoded(brick);
      planes_.resize(3 * voxels_);
      std::uint8_t* r = planes_.data();
      std::uint8_t* g = r + voxels_;
      std::uint8_t* b = g + voxels_;
      const std::uint8_t* p = rgba.data();
      for (std::size_t i = 0; i < voxels_; ++i, p += 4) {
        r[i] = p[0];
        g[i] = p[1];
        b[i] = p[2];
      }
      compress(planes_.data(), planes_.size(), out);
      return;
    }
    case ImageKind::kAlpha: {
      if (constant(brick, 3)) {
        if (brick.min[3] == image.fill_value) return;
        constant_chunk(image, {brick.min[3], 0, 0}, out);
        return;
      }
      const std::vector<std::uint8_t>& rgba = decoded(brick);
      planes_.resize(voxels_);
      for (std::size_t i = 0; i < voxels_; ++i)
        planes_[i] = rgba[4 * i + 3];
      compress(planes_.data(), planes_.size(), out);
      return;
    }
    case ImageKind::kScalar:
    case ImageKind::kLabels: {
      if (constant(brick, 0)) {
        if (brick.min[0] == image.fill_value) return;
        constant_chunk(image, {brick.min[0], 0, 0}, out);
        return;
      }
      const std::size_t bytes = voxels_ * image.item_bytes;
      if (brick.codec == Codec::kRaw) {  // the brick's bytes are the chunk's: compress them
        const ByteView raw = reader_.payload(brick);
        compress(raw.data, raw.size, out);
        return;
      }
      const ByteView stored = reader_.payload(brick);
      // A zstd frame that states its decoded size (a reader sizes its buffer from it) and
      // spans the whole payload is the chunk itself.
      if (copy_stored_ && brick.codec == Codec::kZstd &&
          ZSTD_getFrameContentSize(stored.data, stored.size) == bytes &&
          ZSTD_findFrameCompressedSize(stored.data, stored.size) == stored.size) {
        out.how = EncodedChunk::How::kCopied;
        out.copied = stored;
        return;
      }
      const std::vector<std::uint8_t>& voxels = decoded(brick);
      compress(voxels.data(), bytes, out);
      return;
    }
  }
}

}  // namespace vispack::format::ome_zarr

// PNG files from pixels through libdeflate. See common/png_encode.h.
#include "vispack/common/png_encode.h"

#include <libdeflate.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <stdexcept>
#include <string>

namespace vispack {
namespace {

struct CompressorFree {
  void operator()(libdeflate_compressor* c) const { libdeflate_free_compressor(c); }
};

void put_be32(std::vector<unsigned char>& out, std::uint32_t v) {
  const unsigned char b[4] = {static_cast<unsigned char>(v >> 24),
                              static_cast<unsigned char>(v >> 16),
                              static_cast<unsigned char>(v >> 8), static_cast<unsigned char>(v)};
  out.insert(out.end(), b, b + 4);
}

// One chunk: length, type, data, CRC-32 of type and data (PNG specification, 5.3).
void put_chunk(std::vector<unsigned char>& out, const char type[4], const unsigned char* data,
               std::size_t size) {
  put_be32(out, static_cast<std::uint32_t>(size));
  const std::size_t type_at = out.size();
  out.insert(out.end(), type, type + 4);
  if (size) out.insert(out.end(), data, data + size);
  put_be32(out, static_cast<std::uint32_t>(
                    libdeflate_crc32(0, out.data() + type_at, std::size_t(4) + size)));
}

// Row `y` of `image` as PNG stores it: samples big-endian.
void stored_row(const ImageView& image, std::size_t row_bytes, int y, unsigned char* out) {
  const auto* in = static_cast<const unsigned char*>(image.pixels) + std::size_t(y) * row_bytes;
  const std::size_t size =
      std::size_t(image.width) * std::size_t(image.channels) * std::size_t(image.bits / 8);
  if (image.bits == 8) {
    std::memcpy(out, in, size);
    return;
  }
  for (std::size_t i = 0; i < size; i += 2) {
    std::uint16_t v;
    std::memcpy(&v, in + i, 2);  // native endian, any alignment
    out[i] = static_cast<unsigned char>(v >> 8);
    out[i + 1] = static_cast<unsigned char>(v & 0xff);
  }
}

}  // namespace

std::vector<unsigned char> encode_png(const ImageView& image, int level) {
  if (image.width <= 0 || image.height <= 0 || image.pixels == nullptr)
    throw std::invalid_argument("encode_png: empty image");
  if ((image.bits != 8 && image.bits != 16) ||
      (image.channels != 1 && image.channels != 3 && image.channels != 4))
    throw std::invalid_argument("encode_png: pixels must be 8 or 16 bit, 1, 3 or 4 channels (got " +
                                std::to_string(image.bits) + " bits, " +
                                std::to_string(image.channels) + " channels)");
  if (level < 0 || level > 12)
    throw std::invalid_argument("encode_png: level " + std::to_string(level) + " is outside 0..12");
  const std::size_t row =
      std::size_t(image.width) * std::size_t(image.channels) * std::size_t(image.bits / 8);
  const std::size_t row_bytes = image.row_bytes ? image.row_bytes : row;
  if (row_bytes < row) throw std::invalid_argument("encode_png: row_bytes is below one row");

  // The filtered rows, each after its filter byte (2: Up; the first row's "above" is zeros).
  const std::size_t height = std::size_t(image.height);
  std::vector<unsigned char> filtered(height * (row + 1));
  std::vector<unsigned char> rows(2 * row, 0);  // this row and the one above, as stored
  unsigned char* above = rows.data();
  unsigned char* current = rows.data() + row;
  for (std::size_t y = 0; y < height; ++y) {
    stored_row(image, row_bytes, int(y), current);
    unsigned char* out = filtered.data() + y * (row + 1);
    out[0] = 2;
    for (std::size_t i = 0; i < row; ++i)
      out[1 + i] = static_cast<unsigned char>(current[i] - above[i]);
    std::swap(above, current);
  }

  const std::unique_ptr<libdeflate_compressor, CompressorFree> compressor(
      libdeflate_alloc_compressor(level));
  if (!compressor) throw std::bad_alloc();
  std::vector<unsigned char> stream(
      libdeflate_zlib_compress_bound(compressor.get(), filtered.size()));
  const std::size_t stream_size = libdeflate_zlib_compress(
      compressor.get(), filtered.data(), filtered.size(), stream.data(), stream.size());
  if (stream_size == 0) throw std::bad_alloc();  // cannot happen: the buffer holds the bound
  filtered = {};

  static const unsigned char kSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  constexpr std::size_t kIdatBytes = std::size_t(1) << 20;
  std::vector<unsigned char> png;
  png.reserve(8 + 25 + stream_size + 12 * (stream_size / kIdatBytes + 1) + 12);
  png.insert(png.end(), kSignature, kSignature + 8);
  unsigned char header[13];
  const auto w = static_cast<std::uint32_t>(image.width);
  const auto h = static_cast<std::uint32_t>(image.height);
  for (int i = 0; i < 4; ++i) {
    header[i] = static_cast<unsigned char>(w >> (24 - 8 * i));
    header[4 + i] = static_cast<unsigned char>(h >> (24 - 8 * i));
  }
  header[8] = static_cast<unsigned char>(image.bits);
  header[9] = image.channels == 1 ? 0 : image.channels == 3 ? 2 : 6;  // grey, RGB, RGBA
  header[10] = 0;                                                     // compression: deflate
  header[11] = 0;  // filter method 0 (five row filters; every row here uses Up)
  header[12] = 0;  // not interlaced
  put_chunk(png, "IHDR", header, sizeof header);
  for (std::size_t at = 0; at < stream_size; at += kIdatBytes)
    put_chunk(png, "IDAT", stream.data() + at, std::min(kIdatBytes, stream_size - at));
  put_chunk(png, "IEND", nullptr, 0);
  return png;
}

}  // namespace vispack

// Plain PNGs inflated by libdeflate. See imaging/png_decode.h.
#include "vispack/pipeline/imaging/png_decode.h"

#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <vector>

#include <libdeflate.h>

namespace vispack::pipeline {
namespace {

std::uint32_t be32(const unsigned char* p) {
  return std::uint32_t(p[0]) << 24 | std::uint32_t(p[1]) << 16 | std::uint32_t(p[2]) << 8 | p[3];
}

struct DecompressorFree {
  void operator()(libdeflate_decompressor* d) const { libdeflate_free_decompressor(d); }
};

// The PNG Paeth predictor (PNG specification, 9.4).
inline int paeth(int a, int b, int c) {
  const int p = a + b - c;
  const int pa = std::abs(p - a), pb = std::abs(p - b), pc = std::abs(p - c);
  if (pa <= pb && pa <= pc) return a;
  return pb <= pc ? b : c;
}

// Undoes one row's filter: `in` the filtered bytes, `out` the row (not overlapping `in`),
// `prev` the previous row unfiltered (zeros for the first); B bytes a pixel. The left
// neighbours are kept in locals (one chain per byte of the pixel): the byte just written is not
// read back from memory. Returns false for an unknown filter type.
template <std::size_t B>
bool unfilter_row(int filter, const unsigned char* in, unsigned char* out,
                  const unsigned char* prev, std::size_t size) {
  unsigned char left[B], up_left[B];
  switch (filter) {
    case 0:
      std::memcpy(out, in, size);
      return true;
    case 1:
      for (std::size_t c = 0; c < B; ++c)
        left[c] = out[c] = in[c];
      for (std::size_t i = B; i < size; i += B)
        for (std::size_t c = 0; c < B; ++c)
          left[c] = out[i + c] = static_cast<unsigned char>(in[i + c] + left[c]);
      return true;
    case 2:
      for (std::size_t i = 0; i < size; ++i)
        out[i] = static_cast<unsigned char>(in[i] + prev[i]);
      return true;
    case 3:
      for (std::size_t c = 0; c < B; ++c)
        left[c] = out[c] = static_cast<unsigned char>(in[c] + (prev[c] >> 1));
      for (std::size_t i = B; i < size; i += B)
        for (std::size_t c = 0; c < B; ++c)
          left[c] = out[i + c] =
              static_cast<unsigned char>(in[i + c] + ((left[c] + prev[i + c]) >> 1));
      return true;
    case 4:
      for (std::size_t c = 0; c < B; ++c) {  // paeth(0, b, 0) = b
        left[c] = out[c] = static_cast<unsigned char>(in[c] + prev[c]);
        up_left[c] = prev[c];
      }
      for (std::size_t i = B; i < size; i += B)
        for (std::size_t c = 0; c < B; ++c) {
          const unsigned char up = prev[i + c];
          left[c] = out[i + c] =
              static_cast<unsigned char>(in[i + c] + paeth(left[c], up, up_left[c]));
          up_left[c] = up;
        }
      return true;
    default:
      return false;
  }
}

bool unfilter_row(int filter, const unsigned char* in, unsigned char* out,
                  const unsigned char* prev, std::size_t size, std::size_t bpp) {
  switch (bpp) {
    case 1:
      return unfilter_row<1>(filter, in, out, prev, size);
    case 2:
      return unfilter_row<2>(filter, in, out, prev, size);
    case 3:
      return unfilter_row<3>(filter, in, out, prev, size);
    case 4:
      return unfilter_row<4>(filter, in, out, prev, size);
    case 6:
      return unfilter_row<6>(filter, in, out, prev, size);
    default:
      return unfilter_row<8>(filter, in, out, prev, size);
  }
}

}  // namespace

std::optional<cv::Mat> decode_plain_png(std::string_view bytes, int max_edge,
                                        std::uint64_t max_bytes) {
  static const unsigned char kSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  const auto* data = reinterpret_cast<const unsigned char*>(bytes.data());
  const std::size_t size = bytes.size();
  if (size < 8 + 25 || std::memcmp(data, kSignature, 8) != 0) return std::nullopt;
  // The chunks: IHDR first, the IDATs one after another, IEND; every CRC checked.
  std::size_t at = 8;
  std::uint32_t width = 0, height = 0;
  int depth = 0, colour = 0;
  std::vector<unsigned char> stream;
  stream.reserve(size);
  bool header = false, idat_done = false, end = false;
  while (!end) {
    if (size - at < 12) return std::nullopt;
    const std::uint32_t length = be32(data + at);
    if (length > size - at - 12) return std::nullopt;
    const unsigned char* type = data + at + 4;
    const unsigned char* body = type + 4;
    // A chunk type is four ASCII letters (PNG specification, 5.3); libpng refuses any other.
    for (int i = 0; i < 4; ++i)
      if (!((type[i] >= 'A' && type[i] <= 'Z') || (type[i] >= 'a' && type[i] <= 'z')))
        return std::nullopt;
    if (libdeflate_crc32(0, type, length + 4) != be32(body + length)) return std::nullopt;
    const bool ihdr = std::memcmp(type, "IHDR", 4) == 0;
    const bool idat = std::memcmp(type, "IDAT", 4) == 0;
    if (header == ihdr) return std::nullopt;  // IHDR first, and once
    if (ihdr) {
      if (length != 13) return std::nullopt;
      width = be32(body);
      height = be32(body + 4);
      depth = body[8];
      colour = body[9];
      // Compression 0, filter method 0, not interlaced.
      if (body[10] != 0 || body[11] != 0 || body[12] != 0) return std::nullopt;
      header = true;
    } else if (idat) {
      if (idat_done) return std::nullopt;  // IDATs must follow one another
      stream.insert(stream.end(), body, body + length);
    } else {
      if (!stream.empty()) idat_done = true;
      if (std::memcmp(type, "IEND", 4) == 0) {
        end = true;
      } else if ((type[0] & 0x20) == 0 && std::memcmp(type, "PLTE", 4) != 0) {
        return std::nullopt;  // another critical chunk
      } else if (std::memcmp(type, "tRNS", 4) == 0) {
        return std::nullopt;  // transparency: OpenImageIO's reader decides what it means
      }
    }
    at += 12 + std::size_t(length);
  }
  if (stream.empty() || (depth != 8 && depth != 16)) return std::nullopt;
  int channels = 0;
  switch (colour) {
    case 0:
      channels = 1;
      break;  // grey
    case 2:
      channels = 3;
      break;  // RGB
    case 4:
      channels = 2;
      break;  // grey + alpha
    case 6:
      channels = 4;
      break;  // RGBA
    default:
      return std::nullopt;  // palette or invalid
  }
  if (width == 0 || height == 0 || width > std::uint32_t(max_edge) ||
      height > std::uint32_t(max_edge))
    return std::nullopt;
  const std::size_t bpp = std::size_t(channels) * std::size_t(depth / 8);
  const std::size_t row = std::size_t(width) * bpp;
  // The size guard as read_slice's (slice_io.h): 4 bytes a sample, alpha included.
  if (std::uint64_t(width) * height * std::uint64_t(channels) * 4 > max_bytes) return std::nullopt;
  // The filtered rows, each after its filter byte, inflated at once (the exact length, the
  // stream's Adler-32 checked by libdeflate).
  const std::size_t raw_size = std::size_t(height) * (row + 1);
  const std::unique_ptr<unsigned char[]> raw(new unsigned char[raw_size]);  // every byte written
  const std::unique_ptr<libdeflate_decompressor, DecompressorFree> inflater(
      libdeflate_alloc_decompressor());
  if (!inflater || libdeflate_zlib_decompress(inflater.get(), stream.data(), stream.size(),
                                              raw.get(), raw_size, nullptr) != LIBDEFLATE_SUCCESS)
    return std::nullopt;
  // Each row unfiltered into the image itself (8 bits, no alpha) or into one of two scratch
  // rows, then converted: colour (or grey) kept, alpha dropped; 16-bit samples from big-endian.
  const int kept = channels >= 3 ? 3 : 1;
  cv::Mat image(int(height), int(width), CV_MAKETYPE(depth == 8 ? CV_8U : CV_16U, kept));
  const bool direct = depth == 8 && kept == channels;
  std::vector<unsigned char> scratch(direct ? row : 3 * row, 0);  // zeros, then two rows
  const unsigned char* prev = scratch.data();
  for (std::size_t y = 0; y < height; ++y) {
    const unsigned char* in = raw.get() + y * (row + 1);
    unsigned char* src =
        direct ? image.ptr<unsigned char>(int(y)) : scratch.data() + row * (1 + y % 2);
    if (!unfilter_row(in[0], in + 1, src, prev, row, bpp)) return std::nullopt;
    prev = src;
    if (direct) continue;
    if (depth == 8) {
      unsigned char* dst = image.ptr<unsigned char>(int(y));
      for (std::size_t x = 0; x < width; ++x)
        for (int c = 0; c < kept; ++c)
          dst[x * kept + c] = src[x * channels + c];
    } else {
      std::uint16_t* dst = image.ptr<std::uint16_t>(int(y));
      for (std::size_t x = 0; x < width; ++x)
        for (int c = 0; c < kept; ++c) {
          const unsigned char* s = src + 2 * (x * channels + c);
          dst[x * kept + c] = static_cast<std::uint16_t>(s[0] << 8 | s[1]);
        }
    }
  }
  return image;
}

}  // namespace vispack::pipeline

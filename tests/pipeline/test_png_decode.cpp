// The plain-PNG decoder (imaging/png_decode.h) against images of known pixels: PNG files built
// here row by row with every filter type, each bit depth and colour type it handles; the files it
// declines still read through OpenImageIO (slice_io.h read_slice).
#include <gtest/gtest.h>

#include <cstdint>
#include <cstdlib>
#include <optional>
#include <string>
#include <vector>

#include <libdeflate.h>
#include <opencv2/core.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/imaging/png_decode.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vp = vispack::pipeline;
using vispack::test::TempDir;

namespace {

constexpr int kEdge = 1 << 16;
constexpr std::uint64_t kBytes = std::uint64_t(1) << 31;

void put32(std::string& out, std::uint32_t v) {
  for (int s = 24; s >= 0; s -= 8)
    out += char((v >> s) & 0xff);
}

void chunk(std::string& out, const char* type, const std::string& body) {
  put32(out, std::uint32_t(body.size()));
  const std::string typed = std::string(type, 4) + body;
  out += typed;
  put32(out, libdeflate_crc32(0, typed.data(), typed.size()));
}

int paeth(int a, int b, int c) {
  const int p = a + b - c;
  const int pa = std::abs(p - a), pb = std::abs(p - b), pc = std::abs(p - c);
  if (pa <= pb && pa <= pc) return a;
  return pb <= pc ? b : c;
}

// A PNG of `image` (CV_8U or CV_16U, 1..4 channels in PNG order: grey, grey + alpha, RGB, RGBA),
// row y filtered with filter type y % 5 (none, Sub, Up, Average, Paeth), so that every filter's
// undoing is checked. `interlace` only sets the header's flag (for a declined file).
std::string encode_png(const cv::Mat& image, bool interlace = false) {
  const int channels = image.channels(), depth = image.depth() == CV_16U ? 16 : 8;
  static const int kColour[] = {0, 0, 4, 2, 6};
  const std::size_t bpp = std::size_t(channels * depth / 8), row = image.cols * bpp;
  std::vector<unsigned char> plain(image.rows * row);  // the samples, big-endian
  for (int y = 0; y < image.rows; ++y)
    for (std::size_t i = 0; i < row / (depth / 8); ++i) {
      unsigned char* p = plain.data() + y * row + i * (depth / 8);
      if (depth == 8) {
        p[0] = image.ptr<std::uint8_t>(y)[i];
      } else {
        const std::uint16_t v = image.ptr<std::uint16_t>(y)[i];
        p[0] = static_cast<unsigned char>(v >> 8), p[1] = static_cast<unsigned char>(v & 0xff);
      }
    }
  std::string filtered;
  for (int y = 0; y < image.rows; ++y) {
    const int filter = y % 5;
    filtered += char(filter);
    const unsigned char* cur = plain.data() + y * row;
    const unsigned char* up = y > 0 ? cur - row : nullptr;
    for (std::size_t i = 0; i < row; ++i) {
      const int a = i >= bpp ? cur[i - bpp] : 0, b = up ? up[i] : 0,
                c = up && i >= bpp ? up[i - bpp] : 0;
      const int predicted[] = {0, a, b, (a + b) >> 1, paeth(a, b, c)};
      filtered += char((cur[i] - predicted[filter]) & 0xff);
    }
  }
  libdeflate_compressor* compressor = libdeflate_alloc_compressor(6);
  std::string stream(libdeflate_zlib_compress_bound(compressor, filtered.size()), '\0');
  stream.resize(libdeflate_zlib_compress(compressor, filtered.data(), filtered.size(),
                                         stream.data(), stream.size()));
  libdeflate_free_compressor(compressor);
  std::string png = "\x89PNG\r\n\x1a\n";
  std::string header;
  put32(header, std::uint32_t(image.cols));
  put32(header, std::uint32_t(image.rows));
  header += char(depth);
  header += char(kColour[channels]);
  header += std::string(2, '\0');
  header += char(interlace ? 1 : 0);
  chunk(png, "IHDR", header);
  chunk(png, "tEXt", std::string("Comment\0an ancillary chunk", 26));
  // The stream split over several IDATs, as writers do.
  for (std::size_t at = 0; at < stream.size(); at += 1000)
    chunk(png, "IDAT", stream.substr(at, 1000));
  chunk(png, "IEND", "");
  return png;
}

// Samples with every bit pattern in play, different per channel, row and column.
cv::Mat noise(int width, int height, int type, unsigned seed) {
  cv::Mat image(height, width, type);
  cv::RNG rng(seed);
  rng.fill(image, cv::RNG::UNIFORM, 0, image.depth() == CV_16U ? 65536 : 256);
  // A smooth ramp over part of it, where the predictors matter.
  for (int y = 0; y < height / 2; ++y)
    for (int x = 0; x < width * image.channels(); ++x) {
      if (image.depth() == CV_16U) {
        image.ptr<std::uint16_t>(y)[x] = static_cast<std::uint16_t>(x * 97 + y * 31);
      } else {
        image.ptr<std::uint8_t>(y)[x] = static_cast<std::uint8_t>(x + 3 * y);
      }
    }
  return image;
}

// What read_slice gives for a file of `image`: the colour or grey channels, alpha dropped.
cv::Mat without_alpha(const cv::Mat& image) {
  if (image.channels() == 1 || image.channels() == 3) return image;
  const int kept = image.channels() == 2 ? 1 : 3;
  cv::Mat out(image.size(), CV_MAKETYPE(image.depth(), kept));
  const int pairs[] = {0, 0, 1, 1, 2, 2};
  cv::mixChannels(&image, 1, &out, 1, pairs, std::size_t(kept));
  return out;
}

bool same(const cv::Mat& a, const cv::Mat& b) {
  return a.type() == b.type() && a.size() == b.size() && cv::norm(a, b, cv::NORM_INF) == 0;
}

}  // namespace

TEST(PngDecode, EveryFilterDepthAndColourTypeGivesBackThePixels) {
  TempDir dir;
  unsigned seed = 1;
  for (int depth : {CV_8U, CV_16U}) {
    for (int channels = 1; channels <= 4; ++channels) {
      SCOPED_TRACE(::testing::Message()
                   << "depth " << (depth == CV_8U ? 8 : 16) << ", " << channels << " channels");
      const cv::Mat image = noise(37, 23, CV_MAKETYPE(depth, channels), seed++);
      const std::string png = encode_png(image);
      const std::optional<cv::Mat> decoded = vp::decode_plain_png(png, kEdge, kBytes);
      ASSERT_TRUE(decoded.has_value());
      EXPECT_TRUE(same(*decoded, without_alpha(image)));
      // read_slice takes the same path.
      const std::string path = dir.path() + "/slice.png";
      vispack::write_file_atomic(path, png);
      EXPECT_TRUE(same(vp::read_slice(path), without_alpha(image)));
    }
  }
}

TEST(PngDecode, FilesOfOpenImageIoReadTheSameAsTheirPixels) {
  // write_image (libpng's adaptive filters, zlib level 4) and write_work_image (the Up filter,
  // run-length strategy): what vispack and its phantom write, read back by the decoder.
  TempDir dir;
  for (int type : {CV_8UC1, CV_8UC3, CV_16UC1, CV_16UC3}) {
    const cv::Mat image = noise(301, 97, type, unsigned(type) + 7);
    for (bool work : {false, true}) {
      const std::string path = dir.path() + (work ? "/work.png" : "/slice.png");
      if (work) {
        vp::write_work_image(path, image);
      } else {
        vp::write_image(path, image);
      }
      const std::optional<cv::Mat> decoded =
          vp::decode_plain_png(vispack::read_file(path), kEdge, kBytes);
      ASSERT_TRUE(decoded.has_value()) << "type " << type << (work ? " work" : "");
      EXPECT_TRUE(same(*decoded, image)) << "type " << type << (work ? " work" : "");
    }
  }
}

TEST(PngDecode, FilesItDoesNotHandleAreDeclinedAndStillRead) {
  TempDir dir;
  const cv::Mat image = noise(40, 30, CV_8UC3, 3);
  const std::string png = encode_png(image);
  ASSERT_TRUE(vp::decode_plain_png(png, kEdge, kBytes).has_value());
  // Larger than the caller's limits.
  EXPECT_FALSE(vp::decode_plain_png(png, 39, kBytes).has_value());
  EXPECT_FALSE(vp::decode_plain_png(png, kEdge, 40 * 30 * 3 * 4 - 1).has_value());
  EXPECT_TRUE(vp::decode_plain_png(png, kEdge, 40 * 30 * 3 * 4).has_value());
  // Not a PNG; cut short.
  EXPECT_FALSE(vp::decode_plain_png("GIF89a" + png, kEdge, kBytes).has_value());
  EXPECT_FALSE(vp::decode_plain_png(png.substr(0, png.size() - 12), kEdge, kBytes).has_value());
  // A flipped bit in the pixel stream: the chunk's CRC (and the stream's Adler-32) tell.
  std::string flipped = png;
  const std::size_t idat = flipped.find("IDAT");
  flipped[idat + 40] = char(flipped[idat + 40] ^ 0x10);
  EXPECT_FALSE(vp::decode_plain_png(flipped, kEdge, kBytes).has_value());
  // ... and read_slice refuses it through OpenImageIO, naming the file.
  const std::string path = dir.path() + "/bad.png";
  vispack::write_file_atomic(path, flipped);
  EXPECT_THROW(vp::read_slice(path), vispack::InputError);
  // Interlaced: declined, read by OpenImageIO (the file holds non-interlaced rows under the
  // interlaced flag, so OpenImageIO reads other pixels or fails; either way not this decoder).
  EXPECT_FALSE(vp::decode_plain_png(encode_png(image, true), kEdge, kBytes).has_value());
  // A palette image (written by hand: colour type 3) is declined.
  std::string palette = png;
  palette[8 + 8 + 9] = 3;  // IHDR colour type, its CRC made good again
  const std::string ihdr = palette.substr(12, 17);
  const std::uint32_t crc = libdeflate_crc32(0, ihdr.data(), ihdr.size());
  for (int i = 0; i < 4; ++i)
    palette[29 + std::size_t(i)] = char((crc >> (24 - 8 * i)) & 0xff);
  EXPECT_FALSE(vp::decode_plain_png(palette, kEdge, kBytes).has_value());
}

TEST(PngDecode, ChunkTypeThatIsNotFourLettersIsDeclined) {
  // libpng refuses a chunk whose type is not four ASCII letters ("oF\x01\x00": found by
  // fuzz_png_decode, which checks every accepted file against OpenImageIO); the decoder declines
  // it too, so read_slice refuses it through OpenImageIO instead of reading it.
  const cv::Mat image = noise(13, 9, CV_16UC1, 5);
  const std::string png = encode_png(image);
  ASSERT_TRUE(vp::decode_plain_png(png, kEdge, kBytes).has_value());
  const std::size_t after_ihdr = 8 + 12 + 13;
  for (const char* type : {"oF\x01\x00", "ab1d", "a d "}) {
    std::string odd;
    chunk(odd, type, std::string(9, '\0'));
    const std::string file = png.substr(0, after_ihdr) + odd + png.substr(after_ihdr);
    EXPECT_FALSE(vp::decode_plain_png(file, kEdge, kBytes).has_value()) << type;
  }
  // The same chunk with a letter type is an ancillary chunk the decoder skips.
  std::string letters;
  chunk(letters, "oFFs", std::string(9, '\0'));
  EXPECT_TRUE(vp::decode_plain_png(png.substr(0, after_ihdr) + letters + png.substr(after_ihdr),
                                   kEdge, kBytes)
                  .has_value());
}

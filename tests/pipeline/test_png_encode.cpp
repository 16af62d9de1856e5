// The built-in PNG encoder (common/png_encode.h): random 8- and 16-bit images of 1, 3 and 4
// channels and odd sizes, encoded, then read back by the slice reader's own decoder
// (imaging/png_decode.h: colour kept, alpha dropped) and, in a build with OpenImageIO, by
// OpenImageIO (libpng: every channel, alpha included); both must give the pixels back exactly.
// In the lean build (no OpenImageIO) write_image writes PNG through the encoder and refuses the
// other formats, which is checked instead.
#include <gtest/gtest.h>

#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#ifdef VISPACK_TEST_HAVE_OIIO
#include <OpenImageIO/imageio.h>
#endif

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/png_encode.h"
#include "vispack/pipeline/imaging/png_decode.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vp = vispack::pipeline;
using vispack::test::TempDir;

namespace {

constexpr int kEdge = 1 << 16;
constexpr std::uint64_t kBytes = std::uint64_t(1) << 31;

// Random samples over the whole range of the type (seeded: the same image every run).
cv::Mat random_image(int width, int height, int channels, int bits, std::uint32_t seed) {
  cv::Mat image(height, width, CV_MAKETYPE(bits == 8 ? CV_8U : CV_16U, channels));
  std::mt19937 random(seed);
  for (int y = 0; y < height; ++y) {
    if (bits == 8) {
      auto* row = image.ptr<std::uint8_t>(y);
      for (int i = 0; i < width * channels; ++i)
        row[i] = static_cast<std::uint8_t>(random());
    } else {
      auto* row = image.ptr<std::uint16_t>(y);
      for (int i = 0; i < width * channels; ++i)
        row[i] = static_cast<std::uint16_t>(random());
    }
  }
  return image;
}

vispack::ImageView view_of(const cv::Mat& image) {
  vispack::ImageView view;
  view.width = image.cols;
  view.height = image.rows;
  view.channels = image.channels();
  view.bits = image.depth() == CV_8U ? 8 : 16;
  view.pixels = image.data;
  view.row_bytes = image.step[0];
  return view;
}

// The image's first `channels` channels (the colour of RGBA, the grey of grey).
cv::Mat first_channels(const cv::Mat& image, int channels) {
  if (image.channels() == channels) return image;
  cv::Mat out(image.rows, image.cols, CV_MAKETYPE(image.depth(), channels));
  const int pairs[] = {0, 0, 1, 1, 2, 2};
  cv::mixChannels(&image, 1, &out, 1, pairs, std::size_t(channels));
  return out;
}

// Number of samples that differ (both the same type and size, else every sample).
std::size_t differing_samples(const cv::Mat& a, const cv::Mat& b) {
  if (a.type() != b.type() || a.size() != b.size()) return a.total() * a.channels();
  cv::Mat diff;
  cv::compare(a.reshape(1), b.reshape(1), diff, cv::CMP_NE);
  return std::size_t(cv::countNonZero(diff));
}

// The chunk types of a PNG file, in order.
std::vector<std::string> chunk_types(const std::vector<unsigned char>& png) {
  std::vector<std::string> types;
  std::size_t at = 8;
  while (at + 12 <= png.size()) {
    const std::uint32_t length = std::uint32_t(png[at]) << 24 | std::uint32_t(png[at + 1]) << 16 |
                                 std::uint32_t(png[at + 2]) << 8 | png[at + 3];
    types.emplace_back(reinterpret_cast<const char*>(png.data() + at + 4), 4);
    at += 12 + std::size_t(length);
  }
  EXPECT_EQ(at, png.size()) << "chunks do not end at the end of the file";
  return types;
}

#ifdef VISPACK_TEST_HAVE_OIIO
// The file as OpenImageIO reads it: every channel, colour as stored next to an alpha.
cv::Mat read_with_oiio(const std::string& path) {
  OIIO::ImageSpec config;
  config.attribute("oiio:UnassociatedAlpha", 1);
  auto input = OIIO::ImageInput::open(path, &config);
  if (!input) {
    ADD_FAILURE() << path << ": " << OIIO::geterror();
    return {};
  }
  const OIIO::ImageSpec& spec = input->spec();
  const bool wide = spec.format == OIIO::TypeDesc::UINT16;
  cv::Mat image(spec.height, spec.width, CV_MAKETYPE(wide ? CV_16U : CV_8U, spec.nchannels));
  if (!input->read_image(0, 0, 0, spec.nchannels,
                         wide ? OIIO::TypeDesc::UINT16 : OIIO::TypeDesc::UINT8, image.data))
    ADD_FAILURE() << path << ": " << input->geterror();
  return image;
}
#endif

struct Case {
  int width, height, channels, bits;
};

const Case kCases[] = {
    {1, 1, 1, 8},     {1, 1, 3, 16},   {1, 1, 4, 8},     {3, 7, 1, 8},    {3, 7, 1, 16},
    {3, 7, 3, 8},     {3, 7, 3, 16},   {3, 7, 4, 8},     {3, 7, 4, 16},   {2053, 3, 1, 8},
    {2053, 3, 1, 16}, {2053, 3, 3, 8}, {2053, 3, 3, 16}, {2053, 3, 4, 8}, {2053, 3, 4, 16},
};

std::string cat_name(const Case& c, int level) {
  return std::to_string(c.width) + "x" + std::to_string(c.height) + "x" +
         std::to_string(c.channels) + "_" + std::to_string(c.bits) + "bit_level" +
         std::to_string(level);
}

}  // namespace

TEST(PngEncode, RandomImagesReadBackPixelIdentical) {
  TempDir dir("png-encode");
  std::uint32_t seed = 1;
  for (const Case& c : kCases) {
    for (int level : {0, 1, 6, 12}) {
      const std::string name = cat_name(c, level);
      SCOPED_TRACE(name);
      const cv::Mat image = random_image(c.width, c.height, c.channels, c.bits, seed++);
      const std::vector<unsigned char> png = vispack::encode_png(view_of(image), level);
      EXPECT_EQ(chunk_types(png), (std::vector<std::string>{"IHDR", "IDAT", "IEND"}));
      EXPECT_EQ(vispack::encode_png(view_of(image), level), png) << "bytes not deterministic";

      // The own decoder: colour (or grey) kept, alpha dropped.
      const std::string_view bytes(reinterpret_cast<const char*>(png.data()), png.size());
      const auto decoded = vp::decode_plain_png(bytes, kEdge, kBytes);
      ASSERT_TRUE(decoded) << "the own decoder declines the file";
      const int kept = c.channels == 4 ? 3 : c.channels;
      EXPECT_EQ(differing_samples(*decoded, first_channels(image, kept)), 0u);

#ifdef VISPACK_TEST_HAVE_OIIO
      // OpenImageIO (libpng): every channel, alpha included.
      const std::string path = dir.path() + "/" + name + ".png";
      vispack::write_file_atomic(path, png.data(), png.size());
      EXPECT_EQ(differing_samples(read_with_oiio(path), image), 0u);
#endif
    }
  }
}

TEST(PngEncode, RowsApartByRowBytesAreReadFromTheirStride) {
  // A view into a wider image: rows row_bytes apart, more than one row's samples.
  const cv::Mat wide = random_image(40, 9, 3, 16, 77);
  const cv::Mat part = wide(cv::Rect(5, 2, 17, 6));
  ASSERT_GT(part.step[0], std::size_t(17 * 3 * 2));
  const std::vector<unsigned char> png = vispack::encode_png(view_of(part), 4);
  const std::string_view bytes(reinterpret_cast<const char*>(png.data()), png.size());
  const auto decoded = vp::decode_plain_png(bytes, kEdge, kBytes);
  ASSERT_TRUE(decoded);
  EXPECT_EQ(differing_samples(*decoded, part.clone()), 0u);
}

TEST(PngEncode, RefusesWhatPngCannotHoldHere) {
  const cv::Mat grey_alpha = random_image(4, 4, 2, 8, 3);
  EXPECT_THROW(vispack::encode_png(view_of(grey_alpha), 4), std::invalid_argument);
  const cv::Mat image = random_image(4, 4, 1, 8, 3);
  EXPECT_THROW(vispack::encode_png(view_of(image), 13), std::invalid_argument);
  vispack::ImageView empty = view_of(image);
  empty.pixels = nullptr;
  EXPECT_THROW(vispack::encode_png(empty, 4), std::invalid_argument);
}

#ifndef VISPACK_TEST_HAVE_OIIO
// The lean build: write_image writes PNG through the encoder, read_slice reads it back through
// the own decoder; TIFF, JPEG and BMP are refused naming the file.
TEST(PngEncode, LeanBuildWritesPngAndRefusesOtherFormats) {
  TempDir dir("png-encode-lean");
  const cv::Mat image = random_image(31, 5, 3, 16, 9);
  const std::string png = dir.path() + "/slice.png";
  vp::write_image(png, image);
  EXPECT_EQ(differing_samples(vp::read_slice(png), image), 0u);
  EXPECT_EQ(vp::read_slice_size(png), cv::Size(31, 5));
  for (const char* ext : {".tif", ".jpg", ".bmp"}) {
    const std::string path = dir.path() + "/slice" + ext;
    try {
      vp::write_image(path, first_channels(random_image(4, 4, 3, 8, 1), 3));
      ADD_FAILURE() << path << " was written";
    } catch (const vispack::IoError& e) {
      EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("no OpenImageIO"), std::string::npos) << e.what();
    }
  }
}
#endif

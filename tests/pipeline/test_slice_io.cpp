// Slice I/O: round trips through PNG/TIFF/JPEG and raw layouts, RGB channel order, errors.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vp = vispack::pipeline;
using vispack::test::TempDir;

namespace {

// A deterministic test image with every channel different, so a channel swap shows.
cv::Mat make_image(int width, int height, int type) {
  cv::Mat image(height, width, type);
  const int channels = image.channels();
  const bool sixteen = image.depth() == CV_16U;
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      for (int c = 0; c < channels; ++c) {
        const unsigned v = (x * 7 + y * 13 + c * 101 + x * y) & (sixteen ? 0xffff : 0xff);
        const unsigned value = sixteen ? (v * 257 + c * 4099) & 0xffff : v;
        if (sixteen) {
          image.ptr<std::uint16_t>(y)[x * channels + c] = static_cast<std::uint16_t>(value);
        } else {
          image.ptr<std::uint8_t>(y)[x * channels + c] = static_cast<std::uint8_t>(value);
        }
      }
    }
  }
  return image;
}

bool equal(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size() || a.type() != b.type()) return false;
  return cv::norm(a, b, cv::NORM_INF) == 0;
}

void write_bytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out << bytes;
}

std::string read_bytes(const std::string& path) {
  return vispack::read_file(path);
}

// Expects `fn` to throw E with a message containing `needle`.
template <class E, class Fn>
void expect_error(Fn fn, const std::string& needle) {
  try {
    fn();
    ADD_FAILURE() << "no exception; expected one mentioning " << needle;
  } catch (const E& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
  }
}

}  // namespace

class RoundTrip : public ::testing::TestWithParam<std::tuple<std::string, int>> {};

TEST_P(RoundTrip, LosslessFormatsGiveBackTheSamePixels) {
  const auto [extension, type] = GetParam();
  TempDir dir;
  const cv::Mat image = make_image(37, 23, type);
  const std::string path = dir / ("image" + extension);
  vp::write_image(path, image);
  const cv::Mat back = vp::read_slice(path);
  if (image.channels() == 4) {
    // read_slice drops alpha: compare the colour.
    cv::Mat rgb;
    cv::Mat channels[4];
    cv::split(image, channels);
    cv::merge(channels, 3, rgb);
    EXPECT_TRUE(equal(back, rgb));
  } else {
    EXPECT_TRUE(equal(back, image)) << extension << " type " << type;
  }
}

INSTANTIATE_TEST_SUITE_P(Formats, RoundTrip,
                         ::testing::Combine(::testing::Values(".png", ".tif", ".TIFF"),
                                            ::testing::Values(CV_8UC1, CV_8UC3, CV_16UC1, CV_16UC3,
                                                              CV_8UC4, CV_16UC4)));

TEST(SliceIo, ChannelOrderIsRgbOnDisk) {
  // Round trips cannot tell RGB from BGR (a swap on write and read cancels out), so also read
  // binary PPM files written by hand: PPM stores R, G, B in that order by definition.
  TempDir dir;
  cv::Mat red(4, 4, CV_8UC3, cv::Scalar(255, 0, 0));  // channel 0 = R in vispack's convention
  const std::string path = dir / "red.png";
  vp::write_image(path, red);
  const cv::Mat back = vp::read_slice(path);
  ASSERT_EQ(back.type(), CV_8UC3);
  EXPECT_EQ(back.at<cv::Vec3b>(0, 0), cv::Vec3b(255, 0, 0));
  const std::string ppm = dir / "green.ppm";
  write_bytes(ppm, std::string("P6\n1 1\n255\n") + std::string("\x00\xff\x00", 3));
  const cv::Mat green = vp::read_slice(ppm);
  ASSERT_EQ(green.type(), CV_8UC3);
  EXPECT_EQ(green.at<cv::Vec3b>(0, 0), cv::Vec3b(0, 255, 0));
  const std::string ppm_blue = dir / "blue.ppm";
  write_bytes(ppm_blue, std::string("P6\n1 1\n255\n") + std::string("\x00\x00\xff", 3));
  EXPECT_EQ(vp::read_slice(ppm_blue).at<cv::Vec3b>(0, 0), cv::Vec3b(0, 0, 255));
}

TEST(SliceIo, WriteIsDeterministic) {
  TempDir dir;
  const cv::Mat image = make_image(64, 48, CV_16UC3);
  for (const std::string ext : {".png", ".tif", ".jpg", ".bmp"}) {
    const cv::Mat src = ext == ".jpg" || ext == ".bmp" ? make_image(64, 48, CV_8UC3) : image;
    vp::write_image(dir / ("a" + ext), src);
    // A second apart, so that a time stamp in the file (TIFF's DateTime) always shows.
    if (ext == ".tif") std::this_thread::sleep_for(std::chrono::milliseconds(1100));
    vp::write_image(dir / ("b" + ext), src);
    EXPECT_EQ(read_bytes(dir / ("a" + ext)), read_bytes(dir / ("b" + ext))) << ext;
    if (ext == ".bmp") {
      EXPECT_TRUE(equal(vp::read_slice(dir / ("a" + ext)), src));  // lossless
    }
  }
}

// Work-folder images (write_work_image: Up filter, run-length zlib) are lossless and
// deterministic, and a mask-like image comes out clearly smaller than with the default PNG
// encoding at the same zlib level (0.58x here; 8 kB against 20 kB for a 2048x1216 body mask).
TEST(SliceIo, WorkImagesAreLosslessAndSmallForMasks) {
  TempDir dir;
  for (int type : {CV_8UC1, CV_16UC1, CV_8UC3, CV_16UC3}) {
    const cv::Mat image = make_image(53, 31, type);
    vp::write_work_image(dir / "w.png", image);
    EXPECT_TRUE(equal(vp::read_slice(dir / "w.png"), image)) << "type " << type;
    vp::write_work_image(dir / "w2.png", image);
    EXPECT_EQ(read_bytes(dir / "w.png"), read_bytes(dir / "w2.png")) << "type " << type;
  }
  cv::Mat mask(384, 512, CV_8UC1, cv::Scalar(0));
  cv::ellipse(mask, {256, 192}, {200, 150}, 10.0, 0.0, 360.0, cv::Scalar(255), cv::FILLED);
  cv::circle(mask, {300, 200}, 40, cv::Scalar(0), cv::FILLED);
  vp::write_work_image(dir / "mask_work.png", mask);
  vp::write_image(dir / "mask_default.png", mask, 90, 1);
  EXPECT_TRUE(equal(vp::read_slice(dir / "mask_work.png"), mask));
  const double work = double(read_bytes(dir / "mask_work.png").size());
  const double plain = double(read_bytes(dir / "mask_default.png").size());
  EXPECT_LT(work, 0.7 * plain) << work << " bytes against " << plain;
}

// Work-folder pictures (WorkImageContent::kPicture: Up filter, Huffman-only zlib) are lossless
// and deterministic, and really Huffman-only: with no search for repeats every filtered byte
// costs at least one bit, so a flat mask takes at least width x height / 8 bytes that way, where
// the run-length encoding of kRegions takes a few hundred.
TEST(SliceIo, WorkPicturesAreLosslessAndHuffmanCoded) {
  TempDir dir;
  for (int type : {CV_8UC1, CV_8UC3, CV_16UC3}) {
    const cv::Mat image = make_image(53, 31, type);
    vp::write_work_image(dir / "p.png", image, vp::WorkImageContent::kPicture);
    EXPECT_TRUE(equal(vp::read_slice(dir / "p.png"), image)) << "type " << type;
    vp::write_work_image(dir / "p2.png", image, vp::WorkImageContent::kPicture);
    EXPECT_EQ(read_bytes(dir / "p.png"), read_bytes(dir / "p2.png")) << "type " << type;
  }
  cv::Mat mask(384, 512, CV_8UC1, cv::Scalar(0));
  cv::ellipse(mask, {256, 192}, {200, 150}, 10.0, 0.0, 360.0, cv::Scalar(255), cv::FILLED);
  vp::write_work_image(dir / "mask_picture.png", mask, vp::WorkImageContent::kPicture);
  vp::write_work_image(dir / "mask_regions.png", mask, vp::WorkImageContent::kRegions);
  EXPECT_TRUE(equal(vp::read_slice(dir / "mask_picture.png"), mask));
  const double picture = double(read_bytes(dir / "mask_picture.png").size());
  const double regions = double(read_bytes(dir / "mask_regions.png").size());
  EXPECT_GE(picture, mask.total() / 8.0) << picture << " bytes (Huffman-only)";
  EXPECT_LT(regions, 0.1 * picture) << regions << " bytes (run-length) against " << picture;
}

TEST(SliceIo, JpegIsCloseAndQualityMatters) {
  TempDir dir;
  // A smooth image: JPEG at quality 95 stays within a few levels (8x8 DCT quantisation).
  cv::Mat image(64, 64, CV_8UC3);
  for (int y = 0; y < 64; ++y)
    for (int x = 0; x < 64; ++x)
      image.at<cv::Vec3b>(y, x) = cv::Vec3b(x * 3, y * 3, 128);
  vp::write_image(dir / "q95.jpg", image, 95);
  vp::write_image(dir / "q10.jpg", image, 10);
  const cv::Mat hi = vp::read_slice(dir / "q95.jpg");
  const cv::Mat lo = vp::read_slice(dir / "q10.jpg");
  ASSERT_EQ(hi.type(), CV_8UC3);
  const double err_hi = cv::norm(hi, image, cv::NORM_L1) / image.total() / 3;
  const double err_lo = cv::norm(lo, image, cv::NORM_L1) / image.total() / 3;
  EXPECT_LT(err_hi, 3.0);  // mean abs error per sample, quality 95 on a smooth ramp
  EXPECT_GT(err_lo, err_hi);
  EXPECT_LT(std::filesystem::file_size(dir / "q10.jpg"),
            std::filesystem::file_size(dir / "q95.jpg"));
}

TEST(SliceIo, RawPlanarInterleavedAndBigEndian) {
  TempDir dir;
  struct Case {
    int channels, bits;
    bool planar, big;
    std::uint64_t header;
  };
  for (const Case& c :
       {Case{3, 8, true, false, 0}, Case{3, 8, false, false, 0}, Case{3, 16, true, true, 0},
        Case{1, 16, false, true, 12}, Case{1, 8, false, false, 7}, Case{3, 16, false, false, 0}}) {
    vp::RawLayout layout;
    layout.width = 19;
    layout.height = 11;
    layout.channels = c.channels;
    layout.bits = c.bits;
    layout.planar = c.planar;
    layout.big_endian = c.big;
    layout.header_bytes = c.header;
    const cv::Mat image = make_image(19, 11, CV_MAKETYPE(c.bits == 8 ? CV_8U : CV_16U, c.channels));
    const std::string path = dir / "slice.raw";
    vp::write_raw_slice(path, image, layout);
    EXPECT_EQ(std::filesystem::file_size(path), c.header + 19 * 11 * c.channels * c.bits / 8);
    EXPECT_TRUE(equal(vp::read_slice(path, layout), image))
        << c.channels << " " << c.bits << " planar " << c.planar << " big " << c.big;
  }
}

TEST(SliceIo, RawByteLayoutIsWhatNlmFilesUse) {
  // Planar 8-bit: all R, then all G, then all B. 16-bit big-endian: high byte first.
  TempDir dir;
  vp::RawLayout planar{2, 1, 3, true, 8, false, 0};
  write_bytes(dir / "p.raw", std::string("\x01\x02\x03\x04\x05\x06", 6));
  const cv::Mat p = vp::read_slice(dir / "p.raw", planar);
  EXPECT_EQ(p.at<cv::Vec3b>(0, 0), cv::Vec3b(1, 3, 5));
  EXPECT_EQ(p.at<cv::Vec3b>(0, 1), cv::Vec3b(2, 4, 6));
  vp::RawLayout big{1, 1, 1, false, 16, true, 0};
  write_bytes(dir / "b.raw", std::string("\x12\x34", 2));
  EXPECT_EQ(vp::read_slice(dir / "b.raw", big).at<std::uint16_t>(0, 0), 0x1234);
  big.big_endian = false;
  EXPECT_EQ(vp::read_slice(dir / "b.raw", big).at<std::uint16_t>(0, 0), 0x3412);
}

namespace {

// A GE Genesis image as the NLM male's CT files are (genesis.h): "IMGF", then big-endian int32
// pixel offset, width, height, depth and compression, filler up to the offset (0xA5: read as
// pixels it shows), then the big-endian 16-bit samples of `image`.
std::string genesis_file(const cv::Mat& image, std::int32_t offset, std::int32_t width,
                         std::int32_t height, std::int32_t depth = 16, std::int32_t compression = 0,
                         const char* magic = "IMGF") {
  std::string bytes(magic, 4);
  for (std::int32_t v : {offset, width, height, depth, compression})
    for (int shift : {24, 16, 8, 0})
      bytes += char(std::uint32_t(v) >> shift & 0xff);
  bytes.resize(std::size_t(std::max<std::int32_t>(offset, 24)), char(0xA5));
  for (int y = 0; y < image.rows; ++y)
    for (int x = 0; x < image.cols; ++x) {
      const std::uint16_t v = image.at<std::uint16_t>(y, x);
      bytes += char(v >> 8);
      bytes += char(v & 0xff);
    }
  return bytes;
}

vp::RawLayout genesis_layout(int width, int height) {
  vp::RawLayout layout;
  layout.width = width;
  layout.height = height;
  layout.channels = 1;
  layout.bits = 16;
  layout.big_endian = true;
  layout.genesis = true;
  return layout;
}

}  // namespace

// raw.header "genesis": the samples start where the file's own header says (3416 bytes as
// commonly quoted for the male's .fre files, or any other offset), with the header's width,
// height and depth checked against the config; a file that is not one, a header cut short, an
// offset outside the file, dims or depth that disagree and a compressed file are refused naming
// the file and the field.
TEST(SliceIo, GenesisHeaderGivesThePixelOffsetAndIsCheckedAgainstTheConfig) {
  TempDir dir;
  const cv::Mat image = make_image(19, 11, CV_16UC1);
  const vp::RawLayout layout = genesis_layout(19, 11);
  for (std::int32_t offset : {3416, 7904, 24}) {
    write_bytes(dir / "c_vm1001.fre", genesis_file(image, offset, 19, 11));
    EXPECT_TRUE(equal(vp::read_slice(dir / "c_vm1001.fre", layout), image)) << "offset " << offset;
  }
  const std::string path = dir / "bad.fre";
  auto refused = [&](const std::string& bytes, const std::string& needle) {
    write_bytes(path, bytes);
    expect_error<vispack::InputError>([&] { vp::read_slice(path, layout); }, path + ": " + needle);
  };
  refused(genesis_file(image, 3416, 19, 11, 16, 0, "IMGX"),
          "not a GE Genesis image: starts with \"IMGX\", not the magic \"IMGF\"");
  refused(genesis_file(image, 3416, 19, 11).substr(0, 14), "GE Genesis header truncated: 14 bytes");
  refused(genesis_file(image, 3416, 19, 11).substr(0, 3000),
          "GE Genesis header field pixel data offset (bytes 4..7) is 3416: outside the file's "
          "3000 bytes");
  refused(genesis_file(image, 3416, 19, 11).substr(0, 3416 + 100),
          "raw slice has 3516 bytes, expected 3834 (19x11x1 at 16 bit, header 3416 bytes by its "
          "GE Genesis header)");
  refused(genesis_file(image, 3416, 11, 19),
          "GE Genesis header field width is 11, the config's raw.width is 19");
  refused(genesis_file(image, 3416, 19, 12),
          "GE Genesis header field height is 12, the config's raw.height is 11");
  refused(genesis_file(image, 3416, 19, 11, 8),
          "GE Genesis header field depth is 8, the "
          "config's raw.bits is 16");
  refused(genesis_file(image, 3416, 19, 11, 16, 3),
          "GE Genesis header field compression (bytes 20..23) is 3: only 0 (none) and 1");
}

// `bytes` (genesis_file) with an image header at byte `at` (the int32 at 148..151) recording
// pixels of x_mm by y_mm (big-endian float32 at its bytes 50..57).
std::string with_pixel_size(std::string bytes, std::int32_t at, float x_mm, float y_mm) {
  auto put = [&](std::size_t where, std::uint32_t v) {
    for (int i = 0; i < 4; ++i)
      bytes[where + std::size_t(i)] = char(v >> (24 - 8 * i) & 0xff);
  };
  std::uint32_t x = 0, y = 0;
  std::memcpy(&x, &x_mm, 4);
  std::memcpy(&y, &y_mm, 4);
  put(148, std::uint32_t(at));
  put(std::size_t(at) + 50, x);
  put(std::size_t(at) + 54, y);
  return bytes;
}

// The pixel size a Genesis image header records against ct.pixel_spacing_mm (the config loader
// hands it to the CT's raw layout): within 1 % the file is read; a clear mismatch (another field
// of view) is refused naming the file, both sizes and the key; a file without an image header
// before its pixels, or a layout without the CT's spacing, is read as before.
TEST(SliceIo, GenesisPixelSizeIsCheckedAgainstTheCtPixelSpacing) {
  TempDir dir;
  const cv::Mat image = make_image(19, 11, CV_16UC1);
  vp::RawLayout layout = genesis_layout(19, 11);
  layout.genesis_pixel_mm = std::array<double, 2>{0.9375, 0.9375};
  const std::string path = dir / "c_vm1001.fre";
  write_bytes(path, with_pixel_size(genesis_file(image, 3416, 19, 11), 2184, 0.94f, 0.9375f));
  EXPECT_TRUE(equal(vp::read_slice(path, layout), image));
  write_bytes(path, with_pixel_size(genesis_file(image, 3416, 19, 11), 2184, 0.9375f, 0.5f));
  expect_error<vispack::InputError>(
      [&] { vp::read_slice(path, layout); },
      path +
          ": GE Genesis image header (at byte 2184) records pixels of 0.9375 x 0.5 mm, the "
          "config's ct.pixel_spacing_mm is [0.9375, 0.9375]");
  vp::RawLayout no_spacing = layout;
  no_spacing.genesis_pixel_mm.reset();
  EXPECT_TRUE(equal(vp::read_slice(path, no_spacing), image));
  // No image header before the pixels (offset 0, or one whose fields would lie in the pixels).
  write_bytes(path, with_pixel_size(genesis_file(image, 3416, 19, 11), 0, 0, 0));
  EXPECT_TRUE(equal(vp::read_slice(path, layout), image));
  write_bytes(path,
              with_pixel_size(genesis_file(image, 3416, 19, 11), 3400, 0.5f, 0.5f).substr(0, 3416) +
                  genesis_file(image, 3416, 19, 11).substr(3416));
  EXPECT_TRUE(equal(vp::read_slice(path, layout), image));
}

// Without raw.header "genesis", a Genesis file read with a header_bytes that is not its pixel
// offset is refused naming both (the size check alone would pass a file whose header is as long
// as header_bytes says but whose pixels start elsewhere); the right header_bytes reads it.
TEST(SliceIo, GenesisFileReadWithTheWrongHeaderBytesIsRefused) {
  TempDir dir;
  const cv::Mat image = make_image(19, 11, CV_16UC1);
  vp::RawLayout layout = genesis_layout(19, 11);
  layout.genesis = false;
  // The pixels at byte 3400 and 16 bytes after them: the size header_bytes 3416 expects, the
  // samples read 16 bytes late.
  write_bytes(dir / "c.fre", genesis_file(image, 3400, 19, 11) + std::string(16, '\0'));
  layout.header_bytes = 3416;
  expect_error<vispack::InputError>(
      [&] { vp::read_slice(dir / "c.fre", layout); },
      "c.fre: a GE Genesis image (magic IMGF) whose header puts the pixels at byte 3400, but "
      "raw.header_bytes is 3416; set raw.header to \"genesis\"");
  write_bytes(dir / "c.fre", genesis_file(image, 3416, 19, 11));
  EXPECT_TRUE(equal(vp::read_slice(dir / "c.fre", layout), image));
}

TEST(SliceIo, SizeFromTheHeaderAlone) {
  TempDir dir;
  const cv::Mat image = make_image(37, 23, CV_8UC3);
  for (const std::string ext : {".png", ".tif"}) {
    vp::write_image(dir / ("s" + ext), image);
    EXPECT_EQ(vp::read_slice_size(dir / ("s" + ext)), cv::Size(37, 23)) << ext;
  }
  vp::RawLayout raw{37, 23, 3, true, 8, false, 0};
  EXPECT_EQ(vp::read_slice_size(dir / "any.raw", raw), cv::Size(37, 23));
  write_bytes(dir / "junk.png", "not an image");
  expect_error<vispack::InputError>([&] { vp::read_slice_size(dir / "junk.png"); }, "junk.png");
}

TEST(SliceIo, Errors) {
  TempDir dir;
  write_bytes(dir / "empty.png", "");
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "empty.png"); }, "empty.png");
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "missing.png"); }, "missing.png");

  // A PNG cut in half.
  vp::write_image(dir / "full.png", make_image(64, 64, CV_8UC3));
  const std::string bytes = read_bytes(dir / "full.png");
  write_bytes(dir / "cut.png", bytes.substr(0, bytes.size() / 2));
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "cut.png"); }, "cut.png");
  write_bytes(dir / "junk.png", "this is not an image at all, just text");
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "junk.png"); }, "junk.png");

  // Raw of the wrong size.
  vp::RawLayout layout{4, 4, 3, true, 8, false, 0};
  write_bytes(dir / "short.raw", std::string(47, '\0'));
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "short.raw", layout); },
                                    "expected 48");
  // Hostile raw sizes are refused before allocating.
  vp::RawLayout huge{100000, 10, 1, false, 8, false, 0};
  write_bytes(dir / "huge.raw", std::string(10, '\0'));
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "huge.raw", huge); }, "limit");

  expect_error<vispack::IoError>(
      [&] { vp::write_image(dir / "x.bmpx", make_image(4, 4, CV_8UC3)); }, "x.bmpx");
  expect_error<vispack::IoError>(
      [&] { vp::write_image(dir / "no/such/dir/x.png", make_image(4, 4, CV_8UC3)); }, "x.png");
  // Nothing half-written is left behind by a failed write.
  EXPECT_FALSE(std::filesystem::exists(dir / "x.bmpx"));
}

TEST(SliceIo, HugeHeaderIsRefused) {
  // A PNG whose IHDR claims 70000 x 70000 pixels (a decompression bomb) is refused by the size
  // check with a message about the limit, not by running out of memory.
  TempDir dir;
  vp::write_image(dir / "small.png", make_image(8, 8, CV_8UC1));
  std::string bytes = read_bytes(dir / "small.png");
  // IHDR data starts at byte 16: width (4 bytes BE), height (4 bytes BE). Fix the CRC too.
  const unsigned w = 70000, h = 70000;
  for (int i = 0; i < 4; ++i) {
    bytes[16 + i] = static_cast<char>((w >> (24 - 8 * i)) & 0xff);
    bytes[20 + i] = static_cast<char>((h >> (24 - 8 * i)) & 0xff);
  }
  // CRC-32 over chunk type + data (bytes 12..28 exclusive of length).
  std::uint32_t crc = 0xffffffffu;
  for (int i = 12; i < 29; ++i) {
    crc ^= static_cast<unsigned char>(bytes[i]);
    for (int k = 0; k < 8; ++k)
      crc = (crc >> 1) ^ (0xedb88320u & (0u - (crc & 1u)));
  }
  crc ^= 0xffffffffu;
  for (int i = 0; i < 4; ++i)
    bytes[29 + i] = static_cast<char>((crc >> (24 - 8 * i)) & 0xff);
  write_bytes(dir / "bomb.png", bytes);
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "bomb.png"); }, "bomb.png");
}

TEST(SliceIo, HugeRunLengthBmpIsRefusedBeforeTheDecoder) {
  // A BMP whose header claims 603979787 x 7 pixels, run-length encoded: OpenImageIO's reader
  // decodes it inside open() and threw std::length_error (found by fuzz_raw_slice). Refused by the
  // size check with an error naming the file, for the pixels and for the size alone; the BMP it
  // was made from still reads.
  TempDir dir;
  const std::string good = dir / "good.bmp";
  vp::write_image(good, make_image(9, 5, CV_8UC3));
  std::string bytes = read_bytes(good);
  const unsigned width = 603979787u;
  for (int i = 0; i < 4; ++i)
    bytes[18 + i] = static_cast<char>((width >> (8 * i)) & 0xff);
  bytes[30] = 2;  // BI_RLE4
  write_bytes(dir / "huge.bmp", bytes);
  expect_error<vispack::InputError>([&] { vp::read_slice(dir / "huge.bmp"); }, "huge.bmp");
  expect_error<vispack::InputError>([&] { vp::read_slice_size(dir / "huge.bmp"); }, "huge.bmp");
  EXPECT_EQ(vp::read_slice(good).size(), cv::Size(9, 5));
}

namespace {

// A BMP written byte by byte: BITMAPINFOHEADER, `palette` (grey levels) as its colour table and
// `pixels` as its pixel data, stored as given (uncompressed rows or a run-length stream).
std::string make_bmp(int width, int height, int bits, int compression,
                     const std::vector<int>& palette, const std::string& pixels) {
  std::string out;
  auto put = [&](std::uint32_t v, int bytes) {
    for (int i = 0; i < bytes; ++i)
      out += static_cast<char>((v >> (8 * i)) & 0xff);
  };
  const std::uint32_t offset = 14 + 40 + 4 * std::uint32_t(palette.size());
  out += "BM";
  put(offset + std::uint32_t(pixels.size()), 4);
  put(0, 4);
  put(offset, 4);
  put(40, 4);
  put(std::uint32_t(width), 4);
  put(std::uint32_t(height), 4);
  put(1, 2);  // planes
  put(std::uint32_t(bits), 2);
  put(std::uint32_t(compression), 4);
  put(std::uint32_t(pixels.size()), 4);
  put(2835, 4);
  put(2835, 4);
  put(std::uint32_t(palette.size()), 4);
  put(0, 4);
  for (int grey : palette)
    put(std::uint32_t(grey) * 0x010101u, 4);
  return out + pixels;
}

}  // namespace

TEST(SliceIo, BmpWhoseCompressionDoesNotFitItsBitsIsRefusedBeforeTheDecoder) {
  // Run-length encoding at 24 bits per pixel: OpenImageIO 2.4 ran it through an empty colour
  // table and crashed (segmentation fault; found by fuzz_raw_slice in CI, 2026-11-26). Refused
  // with an error naming the file and what is wrong, like JPEG inside a BMP and a bit depth BMP
  // does not define; the BMP they were made from still reads.
  TempDir dir;
  const std::string good = dir / "good.bmp";
  vp::write_image(good, make_image(9, 5, CV_8UC3));
  const std::string bytes = read_bytes(good);
  ASSERT_EQ(bytes[28], 24);
  struct Case {
    const char* name;
    int bits;
    int compression;
    const char* needle;
  };
  for (const Case& c : {Case{"rle8-at-24.bmp", 24, 1, "compression 1 (RLE8) at 24 bits"},
                        Case{"rle4-at-24.bmp", 24, 2, "compression 2 (RLE4) at 24 bits"},
                        Case{"rle4-at-8.bmp", 8, 2, "compression 2 (RLE4) at 8 bits"},
                        Case{"jpeg.bmp", 24, 4, "compression 4 (JPEG)"},
                        Case{"seven-bits.bmp", 7, 0, "7 bits per pixel"}}) {
    std::string bad = bytes;
    bad[28] = static_cast<char>(c.bits);
    bad[30] = static_cast<char>(c.compression);
    write_bytes(dir / c.name, bad);
    const std::string message = std::string(c.name) + ": BMP ";
    expect_error<vispack::InputError>([&] { vp::read_slice(dir / c.name); }, message);
    expect_error<vispack::InputError>([&] { vp::read_slice(dir / c.name); }, c.needle);
    expect_error<vispack::InputError>([&] { vp::read_slice_size(dir / c.name); }, c.needle);
  }
  EXPECT_TRUE(equal(vp::read_slice(good), make_image(9, 5, CV_8UC3)));
}

TEST(SliceIo, GreyRunLengthBmpReadsAsItsGreyLevels) {
  // An 8-bit run-length-encoded BMP with a grey colour table: OpenImageIO 2.4 calls it one
  // channel but wrote three bytes per pixel (each row smeared, the last past the buffer's end).
  // vispack reads it as the grey image it holds, every pixel checked; a colour table that is not
  // grey still gives RGB.
  const int width = 7, height = 3;
  std::vector<int> grey(256);
  for (int i = 0; i < 256; ++i)
    grey[i] = 255 - i;
  cv::Mat expected(height, width, CV_8UC1);
  std::string runs;
  for (int row = 0; row < height; ++row) {  // stored bottom-up
    const int y = height - 1 - row;
    runs += std::string{char(0), char(width)};  // an absolute run of `width` indices
    for (int x = 0; x < width; ++x) {
      const int index = 10 * x + 40 * y + 1;
      runs += static_cast<char>(index);
      expected.at<std::uint8_t>(y, x) = static_cast<std::uint8_t>(grey[index]);
    }
    runs += std::string(1, char(0));  // absolute runs pad to an even length
    runs += std::string{char(0), char(row + 1 == height ? 1 : 0)};  // end of line / bitmap
  }
  TempDir dir;
  write_bytes(dir / "grey.bmp", make_bmp(width, height, 8, 1, grey, runs));
  const cv::Mat image = vp::read_slice(dir / "grey.bmp");
  ASSERT_EQ(image.type(), CV_8UC1);
  EXPECT_TRUE(equal(image, expected)) << image << "\n" << expected;

  std::string colour = make_bmp(width, height, 8, 1, grey, runs);
  colour[54 + 4] = 0x56;  // entry 1 (B, G, R) no longer grey: the table is a colour one
  colour[54 + 5] = 0x34;
  colour[54 + 6] = 0x12;
  write_bytes(dir / "colour.bmp", colour);
  const cv::Mat rgb = vp::read_slice(dir / "colour.bmp");
  ASSERT_EQ(rgb.type(), CV_8UC3);
  EXPECT_EQ(rgb.at<cv::Vec3b>(0, 0), cv::Vec3b(0x12, 0x34, 0x56));  // index 1, in RGB order
  cv::Mat green;
  cv::extractChannel(rgb, green, 1);
  expected.at<std::uint8_t>(0, 0) = 0x34;
  EXPECT_TRUE(equal(green, expected));
}

TEST(SliceIo, FormatIsToldByTheFirstBytesAndOnlyItsReaderIsTried) {
  // OpenImageIO, handed a file its named reader refuses, tries every other reader it has. A
  // Targa image (no magic number) named .png was read by its Targa reader; vispack refuses it,
  // naming the file and its first bytes. A PNM named .png is read by the PNM reader, as its bytes
  // say; a PNG named .tif likewise.
  TempDir dir;
  const std::string targa(
      "\x00\x00\x02\x00\x00\x00\x00\x00\x00\x00\x00\x00\x02\x00\x01\x00\x18\x20"
      "\x01\x02\x03\x04\x05\x06",
      24);
  write_bytes(dir / "targa.png", targa);
  for (auto read : {+[](const std::string& p) { vp::read_slice(p); },
                    +[](const std::string& p) { vp::read_slice_size(p); }}) {
    expect_error<vispack::InputError>([&] { read(dir / "targa.png"); },
                                      "targa.png: cannot read slice: not a PNG, TIFF, JPEG, BMP "
                                      "or PNM image (first bytes 00 00 02 00 00 00 00 00)");
  }
  write_bytes(dir / "pnm.png",
              std::string("P6\n2 1\n255\n") + std::string("\x01\x02\x03\x04\x05\x06", 6));
  const cv::Mat pnm = vp::read_slice(dir / "pnm.png");
  ASSERT_EQ(pnm.type(), CV_8UC3);
  EXPECT_EQ(pnm.at<cv::Vec3b>(0, 1), cv::Vec3b(4, 5, 6));
  const cv::Mat image = make_image(5, 4, CV_16UC1);
  vp::write_image(dir / "png.png", image);
  std::filesystem::rename(dir / "png.png", dir / "png.tif");
  EXPECT_TRUE(equal(vp::read_slice(dir / "png.tif"), image));
  EXPECT_EQ(vp::read_slice_size(dir / "png.tif"), cv::Size(5, 4));
}

TEST(ListSlices, NumericSortAndPatternMatching) {
  TempDir dir;
  for (const char* name : {"rgb_10.png", "rgb_2.png", "rgb_0001.png", "rgb_x.png", "other_3.png",
                           "rgb_4.png.bak", "rgb_.png"}) {
    write_bytes(dir / name, "x");
  }
  std::filesystem::create_directory(dir / "rgb_5.png");  // a folder is not a slice
  vp::SliceSource source;
  source.dir = dir.path();
  source.pattern = "rgb_{n}.png";
  const auto files = vp::list_slices(source);
  ASSERT_EQ(files.size(), 3u);
  EXPECT_EQ(files[0].number, 1);
  EXPECT_EQ(files[1].number, 2);
  EXPECT_EQ(files[2].number, 10);
  EXPECT_EQ(files[1].path, dir / "rgb_2.png");
  EXPECT_EQ(files[2].path, dir / "rgb_10.png");
}

TEST(ListSlices, Errors) {
  TempDir dir;
  vp::SliceSource source;
  source.dir = dir / "nope";
  source.pattern = "rgb_{n}.png";
  expect_error<vispack::ConfigError>([&] { vp::list_slices(source); }, dir / "nope");
  source.dir = dir.path();
  write_bytes(dir / "ct_1.png", "x");
  expect_error<vispack::ConfigError>([&] { vp::list_slices(source); }, "rgb_{n}.png");
  write_bytes(dir / "rgb_7.png", "x");
  write_bytes(dir / "rgb_007.png", "x");
  expect_error<vispack::ConfigError>([&] { vp::list_slices(source); }, "rgb_007.png");
  source.pattern = "rgb_.png";
  expect_error<vispack::ConfigError>([&] { vp::list_slices(source); }, "{n}");
}

// Fuzz target: the slice reader — header-less raw slices with any declared layout, and PNG/TIFF/
// JPEG/BMP/PNM through OpenImageIO. Input: 8 bytes choosing the layout/format, then the file's
// bytes. Any input must give a cv::Mat of the declared size or an InputError — never a crash.
#include <opencv2/core.hpp>

#include "fuzz_target.h"
#include "scratch.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/imaging/slice_io.h"

using vispack::pipeline::RawLayout;

namespace {

constexpr std::size_t kPrefix = 8;

RawLayout layout_from(const std::uint8_t* p) {
  RawLayout layout;
  layout.width = 1 + p[0] % 64;
  layout.height = 1 + p[1] % 64;
  layout.channels = (p[2] & 1) ? 3 : 1;
  layout.planar = (p[3] & 1) != 0;
  layout.bits = (p[3] & 2) ? 16 : 8;
  layout.big_endian = (p[3] & 4) != 0;
  layout.header_bytes = p[4] % 32;
  return layout;
}

const char* kExtensions[] = {".png", ".tif", ".jpg", ".bmp"};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < kPrefix) return 0;
  bool raw = (data[5] & 1) == 0;
  std::string path =
      vispack_fuzz_scratch_dir() + "/slice" + (raw ? ".raw" : kExtensions[data[6] % 4]);
  vispack_fuzz_write(path, data + kPrefix, size - kPrefix);
  try {
    if (raw) {
      RawLayout layout = layout_from(data);
      cv::Mat image = vispack::pipeline::read_slice(path, layout);
      if (image.cols != layout.width || image.rows != layout.height ||
          image.channels() != layout.channels)
        std::abort();  // a silently wrong output is a finding too
    } else {
      cv::Mat image = vispack::pipeline::read_slice(path);
      if (image.empty()) std::abort();
    }
  } catch (const vispack::Error&) {
  }
  return 0;
}

void vispack_fuzz_write_seeds(const std::string& dir) {
  // Raw seeds: each declared layout with exactly the right number of bytes.
  for (std::uint8_t mode = 0; mode < 8; ++mode) {
    std::uint8_t prefix[kPrefix] = {
        15, 9, std::uint8_t(mode & 1), std::uint8_t(mode >> 1 | (mode & 1) << 0), 4, 0, 0, 0};
    RawLayout layout = layout_from(prefix);
    std::size_t bytes = layout.header_bytes + std::size_t(layout.width) * layout.height *
                                                  layout.channels * (layout.bits / 8);
    std::vector<std::uint8_t> file(kPrefix + bytes);
    std::copy(prefix, prefix + kPrefix, file.begin());
    for (std::size_t i = kPrefix; i < file.size(); ++i)
      file[i] = std::uint8_t(i * 31);
    vispack_fuzz_write(dir + "/raw-" + std::to_string(mode) + ".bin", file.data(), file.size());
  }
  // Regression: a BMP whose header claims 603979787 x 7 pixels, run-length encoded (OpenImageIO's
  // reader threw std::length_error out of open(); found by a short fuzz run, 2026-11-25).
  static const std::uint8_t kHugeRleBmp[] = {
      0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x03, 0x00, 0x42, 0x4d, 0x32, 0x01, 0x00,
      0x00, 0x00, 0x00, 0x00, 0x00, 0x36, 0x00, 0x00, 0x00, 0x28, 0x00, 0x00, 0x00,
      0x0b, 0x00, 0x00, 0x24, 0x07, 0x00, 0x00, 0x00, 0x01, 0x00, 0x18, 0x00, 0x02,
      0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
      0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
      0x00, 0x00, 0x09, 0x6f, 0x46, 0x46, 0x73, 0x00, 0x00, 0x00, 0x00};
  vispack_fuzz_write(dir + "/regression-huge-rle-bmp.bin", kHugeRleBmp, sizeof kHugeRleBmp);
  // Regression: a BMP run-length encoded (RLE4) at 24 bits per pixel, 11 x 9216 pixels (OpenImageIO
  // 2.4's reader ran its pixels through an empty colour table: a segmentation fault; found by CI's
  // short fuzz run, 2026-11-26). The first 8 bytes choose a .bmp name, then come the file's.
  static const char kRleAt24BitsBmp[] =
      "\x00\x00\x00\x00\x00\x01\x03\x00\x42\x4d\x32\x01\x00\x00\x00\x00"
      "\x00\x00\x36\x00\x00\x00\x28\x00\x00\x00\x0b\x00\x00\x00\x00\x24"
      "\x00\x00\x07\x01\x18\x00\x02\x00\x00\x00\x00\x00\x00\x00\x00\x00"
      "\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00"
      "\x00\x01\x07\x09\x6f\x46\x46\x73\x00\x00\x00\x00";
  vispack_fuzz_write(dir + "/regression-rle-at-24-bits-bmp.bin", kRleAt24BitsBmp,
                     sizeof kRleAt24BitsBmp - 1);
  // Image seeds: a small RGB and a 16-bit grey image in each container.
  cv::Mat rgb(7, 11, CV_8UC3), grey(5, 6, CV_16UC1);
  cv::randu(rgb, 0, 255);
  cv::randu(grey, 0, 65535);
  for (int e = 0; e < 4; ++e) {
    for (int k = 0; k < 2; ++k) {
      const cv::Mat& image = k == 0 ? rgb : grey;
      if (e >= 2 && k == 1) continue;  // JPEG/BMP hold 8-bit only
      std::string tmp = vispack_fuzz_scratch_dir() + "/seed" + kExtensions[e];
      vispack::pipeline::write_image(tmp, image);
      std::string bytes = vispack::read_file(tmp);
      std::string file(kPrefix, '\0');
      file[5] = 1;
      file[6] = char(e);
      file += bytes;
      vispack_fuzz_write(dir + "/image-" + std::to_string(e) + "-" + std::to_string(k) + ".bin",
                         file.data(), file.size());
    }
  }
  // PNM seeds (read by their bytes whatever the name): binary RGB, binary 16-bit grey, ASCII grey.
  const std::string pnms[] = {std::string("P6\n3 2\n255\n") + std::string(18, '\x5a'),
                              std::string("P5\n2 2\n65535\n") + std::string(8, '\x7f'),
                              "P2\n# grey\n2 2\n15\n0 5\n10 15\n"};
  for (int i = 0; i < 3; ++i) {
    std::string file(kPrefix, '\0');
    file[5] = 1;
    file += pnms[i];
    vispack_fuzz_write(dir + "/pnm-" + std::to_string(i) + ".bin", file.data(), file.size());
  }
}

// Fuzz target: the plain-PNG decoder (pipeline/imaging/png_decode.h), against OpenImageIO.
// Input: a PNG file's bytes. The decoder must never crash, and whenever it returns an image, that
// image must be the one OpenImageIO (libpng) reads from the same bytes, alpha dropped: a file the
// fast path accepts and libpng refuses or reads otherwise is a silently wrong slice, a finding.
#include <OpenImageIO/imageio.h>
#include <libdeflate.h>

#include <cstdint>
#include <cstdlib>
#include <string>
#include <string_view>
#include <vector>

#include <opencv2/core.hpp>

#include "fuzz_target.h"
#include "scratch.h"
#include "vispack/common/atomic_file.h"
#include "vispack/pipeline/imaging/png_decode.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace {

constexpr int kMaxEdge = 512;
constexpr std::uint64_t kMaxBytes = std::uint64_t(1) << 24;

// OpenImageIO's pixels of `path` in its own type (8 or 16 bits), every channel, colour as stored
// beside an alpha (as slice_io.cpp reads it); empty when it cannot read the file.
cv::Mat read_with_oiio(const std::string& path) {
  OIIO::ImageSpec config;
  config.attribute("oiio:UnassociatedAlpha", 1);
  auto input = OIIO::ImageInput::open(path, &config);
  if (!input) {
    (void)OIIO::geterror();
    return {};
  }
  const OIIO::ImageSpec& spec = input->spec();
  const bool wide = spec.format.size() == 2;
  const int channels = spec.nchannels;
  if (channels < 1 || channels > 4 || spec.width <= 0 || spec.height <= 0) return {};
  cv::Mat pixels(spec.height, spec.width, CV_MAKETYPE(wide ? CV_16U : CV_8U, channels));
  const bool ok = input->read_image(
      0, 0, 0, channels, wide ? OIIO::TypeDesc::UINT16 : OIIO::TypeDesc::UINT8, pixels.data);
  (void)input->geterror();
  return ok ? pixels : cv::Mat();
}

// `bytes` with every whole chunk's CRC recomputed: a mutated header or chunk order then reaches
// the decoder's checks past the CRC (the pixel stream's Adler-32 still guards mutated pixels).
std::string with_chunk_crcs(std::string bytes) {
  std::size_t at = 8;
  while (bytes.size() >= 12 && at <= bytes.size() - 12) {
    const auto* p = reinterpret_cast<const unsigned char*>(bytes.data() + at);
    const std::uint32_t length =
        std::uint32_t(p[0]) << 24 | std::uint32_t(p[1]) << 16 | std::uint32_t(p[2]) << 8 | p[3];
    if (length > bytes.size() - at - 12) break;
    const std::uint32_t crc = libdeflate_crc32(0, p + 4, std::size_t(length) + 4);
    for (int i = 0; i < 4; ++i)
      bytes[at + 8 + length + i] = char((crc >> (24 - 8 * i)) & 0xff);
    at += 12 + std::size_t(length);
  }
  return bytes;
}

// Whatever the decoder accepts, libpng must read to the same pixels (alpha dropped).
void check(const std::string& bytes) {
  const auto image = vispack::pipeline::decode_plain_png(bytes, kMaxEdge, kMaxBytes);
  if (!image) return;
  const std::string path = vispack_fuzz_scratch_dir() + "/slice.png";
  vispack_fuzz_write(path, bytes.data(), bytes.size());
  cv::Mat reference = read_with_oiio(path);
  if (reference.empty()) std::abort();  // accepted here, refused by libpng
  if (reference.channels() == 2 || reference.channels() == 4) {
    std::vector<cv::Mat> planes;
    cv::split(reference, planes);
    planes.pop_back();  // alpha
    cv::merge(planes, reference);
  }
  if (reference.size() != image->size() || reference.type() != image->type() ||
      cv::norm(reference, *image, cv::NORM_INF) != 0)
    std::abort();  // another image than libpng's
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string bytes(reinterpret_cast<const char*>(data), size);
  check(bytes);
  check(with_chunk_crcs(bytes));
  return 0;
}

void vispack_fuzz_write_seeds(const std::string& dir) {
  // The files vispack writes (OpenImageIO's PNG writer): every type the decoder handles, small
  // enough for the fuzzer to mutate, with a ramp (predictors) and noise (every bit pattern).
  const int types[] = {CV_8UC1, CV_8UC3, CV_8UC4, CV_16UC1, CV_16UC3, CV_16UC4};
  int n = 0;
  for (const int type : types) {
    cv::Mat image(9, 13, type);
    cv::randu(image, 0, CV_MAT_DEPTH(type) == CV_16U ? 65536 : 256);
    for (int x = 0; x < image.cols * image.channels(); ++x)
      image.at<std::uint8_t>(0, x) = static_cast<std::uint8_t>(x * 5);
    const std::string tmp = vispack_fuzz_scratch_dir() + "/seed.png";
    vispack::pipeline::write_image(tmp, image);
    const std::string file = vispack::read_file(tmp);
    vispack_fuzz_write(dir + "/png-" + std::to_string(n++) + ".png", file.data(), file.size());
  }
  // Regression: a 16-bit grey PNG with a chunk typed "oF\x01\x00" (not four letters), accepted by
  // the decoder and refused by libpng (found by this target's first run with CRCs recomputed,
  // 2026-11-27; test PngDecode.ChunkTypeThatIsNotFourLettersIsDeclined).
  static const char kOddChunkType[] =
      "\x89\x50\x4e\x47\x0d\x0a\x1a\x0a\x00\x00\x00\x0d\x49\x48\x44\x52"
      "\x00\x00\x00\x0d\x00\x00\x00\x09\x10\x00\x00\x00\x00\x9c\x81\x25"
      "\xf5\x00\x00\x00\x09\x6f\x46\x01\x00\x00\x00\x00\x00\x00\x00\x00"
      "\x00\x00\xda\x2a\xb6\xce\x00\x00\x00\xfe\x49\x44\x41\x54\x08\x5b"
      "\x01\xf3\x00\x0c\xff\x03\x05\x00\x0d\x0a\x12\x0f\x17\x14\x1c\x19"
      "\x21\x1e\x2f\x23\x04\xc0\xda\x0d\x67\xb5\x63\xde\xe8\x74\x73\xca"
      "\x01\xd5\x96\x14\x9a\xbc\x63\xd2\x68\xe9\x2e\x2e\x67\x92\x49\xa8"
      "\xf2\xda\x09\x4c\xac\x43\x08\xef\x63\x24\x02\x02\x3e\x11\x34\x2a"
      "\xdf\x53\xa1\x64\x78\xb8\x04\x19\x61\xe2\x73\xdb\x8d\x5b\x15\x10"
      "\x0a\xe5\x84\xbc\x44\x30\x00\x9b\x0b\x43\x50\x8d\x18\x17\x3f\x26"
      "\xd5\xbe\xe0\xae\x73\x8a\xee\x46\x01\xbe\xff\x7e\x2a\x20\x0e\x54"
      "\xfd\x02\xfc\x32\x51\xd6\xba\x13\xba\x26\x97\x7c\x12\xe5\x11\xd2"
      "\x26\x0b\x0e\xff\x4f\x58\x0b\x5e\x57\x2c\x0d\x99\x04\x0f\x33\x45"
      "\x33\xa1\x50\xd3\xac\xcf\x35\x44\x02\x28\x73\x15\x69\x24\xcd\x14"
      "\xc5\x78\x94\xfa\xf6\xbc\x8a\x00\xdc\x82\xb9\x3c\xdc\xcd\xee\x3d"
      "\x6d\x18\xf8\x3a\xf4\xd9\xdb\x8d\x51\xe4\x76\x14\x09\xd1\x54\xc5"
      "\x5d\x55\x02\x04\xd4\x78\x4e\xc3\x72\xe5\x72\xbf\x60\xd7\xb2\xc6"
      "\xc1\x89\x69\xb4\x13\x11\x58\xeb\xb4\xd2\xb3\x2a\xc0\x03\xd4\x44"
      "\x29\x01\x8e\xfa\xe3\x5a\x61\x99\x92\xdc\x1c\x26\x5d\x3c\x9f\xad"
      "\xec\xe6\x35\x68\xc5\x55\xd9\xde\x6c\x6f\x6a\xea\xca\xf4\x9d\x2f"
      "\x00\x00\x00\x00\x49\x45\x4e\x44\xae\x42\x60\x82";
  vispack_fuzz_write(dir + "/regression-odd-chunk-type.png", kOddChunkType,
                     sizeof kOddChunkType - 1);
}

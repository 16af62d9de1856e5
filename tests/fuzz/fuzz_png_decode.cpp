// Fuzz target: the plain-PNG decoder (pipeline/imaging/png_decode.h), against OpenImageIO.
// Input: a PNG file's bytes. The decoder must never crash, and whenever it returns an image, that
// image must be the one OpenImageIO (libpng) reads from the same bytes, alpha dropped: a file the
// fast path accepts and libpng refuses or reads otherwise is a silently wrong slice, a finding.
#include <OpenImageIO/imageio.h>

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

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  const auto image = vispack::pipeline::decode_plain_png(bytes, kMaxEdge, kMaxBytes);
  if (!image) return 0;
  const std::string path = vispack_fuzz_scratch_dir() + "/slice.png";
  vispack_fuzz_write(path, data, size);
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
}

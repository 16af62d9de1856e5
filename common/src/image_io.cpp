#include "vispack/common/image_io.h"

#ifdef VISPACK_HAVE_OPENIMAGEIO
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#endif

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <vector>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/png_encode.h"

namespace vispack {
namespace {

std::string extension_of(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  for (char& c : ext)
    c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return ext;
}

#ifdef VISPACK_HAVE_OPENIMAGEIO
// OpenImageIO's messages may span lines; errors here are one line.
std::string one_line(std::string text) {
  std::replace(text.begin(), text.end(), '\n', ' ');
  while (!text.empty() && text.back() == ' ')
    text.pop_back();
  return text;
}
#endif

}  // namespace

void write_image_file(const std::string& path, const ImageView& image,
                      const ImageWriteOptions& options) {
  const std::string ext = extension_of(path);
  std::string format;
  if (ext == ".png") {
    format = "png";
  } else if (ext == ".tif" || ext == ".tiff") {
    format = "tiff";
  } else if (ext == ".jpg" || ext == ".jpeg") {
    format = "jpeg";
  } else if (ext == ".bmp") {
    format = "bmp";
  } else {
    throw IoError(cat(path, ": cannot write image: unsupported extension \"", ext,
                      "\" (use .png, .tif, .tiff, .jpg, .jpeg or .bmp)"));
  }
#ifndef VISPACK_HAVE_OPENIMAGEIO
  // The lean build (VISPACK_WITH_OPENIMAGEIO=OFF, docs/ARCHITECTURE.md "The lean build").
  if (format != "png")
    throw IoError(cat(path, ": cannot write ", format,
                      ": this build has no OpenImageIO (VISPACK_WITH_OPENIMAGEIO=OFF); it writes "
                      "PNG only"));
#endif
  if (image.width <= 0 || image.height <= 0 || image.pixels == nullptr)
    throw IoError(cat(path, ": cannot write an empty image"));
  const int channels = image.channels;
  if ((image.bits != 8 && image.bits != 16) || (channels != 1 && channels != 3 && channels != 4)) {
    throw IoError(cat(path,
                      ": cannot write image: pixel type must be 8 or 16 bit with 1, 3 or 4 "
                      "channels (got ",
                      image.bits, " bits, ", channels, " channels)"));
  }
  if ((format == "jpeg" || format == "bmp") && (image.bits != 8 || channels == 4))
    throw IoError(cat(path, ": cannot write ", format, ": needs 8-bit grey or RGB"));
  if (options.jpeg_quality < 1 || options.jpeg_quality > 100)
    throw IoError(cat(path, ": JPEG quality ", options.jpeg_quality, " is outside 1..100"));
  if (options.png_level < 0 || options.png_level > 9)
    throw IoError(cat(path, ": PNG compression level ", options.png_level, " is outside 0..9"));

#ifndef VISPACK_HAVE_OPENIMAGEIO
  // The lean build: PNG through the built-in encoder (png_encode.h), png_level taken as
  // libdeflate's level, every row with the Up filter whatever png_encoding asks.
  const std::vector<unsigned char> png = encode_png(image, options.png_level);
  write_file_atomic(path, png.data(), png.size());
#else
  const OIIO::TypeDesc type = image.bits == 8 ? OIIO::TypeDesc::UINT8 : OIIO::TypeDesc::UINT16;
  OIIO::ImageSpec spec(image.width, image.height, channels, type);
  if (channels == 4) {
    spec.alpha_channel = 3;
    // PNG stores straight alpha: flag the data as unassociated so that OpenImageIO writes the
    // colour as given. Other formats store the samples as given without the flag.
    if (format == "png") spec.attribute("oiio:UnassociatedAlpha", 1);
  }
  if (format == "png") {
    spec.attribute("png:compressionLevel", options.png_level);
    if (options.png_encoding != PngEncoding::kAdaptive) {
      spec.attribute("png:filter", 32);  // PNG_FILTER_UP
      // Z_RLE or Z_HUFFMAN_ONLY
      spec.attribute("compression",
                     options.png_encoding == PngEncoding::kUpRuns ? "rle" : "huffman");
    }
  } else if (format == "tiff") {
    spec.attribute("compression", "zip");
    // No DateTime tag (OpenImageIO stamps the current time otherwise): the same image gives the
    // same bytes, which resume fingerprints and reproducible outputs rely on.
    spec.attribute("DateTime", "");
  } else if (format == "jpeg") {
    spec.attribute("Compression", cat("jpeg:", options.jpeg_quality));
    spec.attribute("CompressionQuality", options.jpeg_quality);
  }
  auto output = OIIO::ImageOutput::create(format);
  if (!output) throw IoError(cat(path, ": cannot write image: ", one_line(OIIO::geterror())));
  if (!output->supports("ioproxy")) {
    throw IoError(
        cat(path, ": cannot write image: the ", format, " writer cannot write to memory"));
  }
  std::vector<unsigned char> buffer;
  OIIO::Filesystem::IOVecOutput proxy(buffer);
  if (!output->set_ioproxy(&proxy) || !output->open(path, spec, OIIO::ImageOutput::Create))
    throw IoError(cat(path, ": cannot write image: ", one_line(output->geterror())));
  const OIIO::stride_t row_bytes =
      image.row_bytes ? OIIO::stride_t(image.row_bytes) : OIIO::AutoStride;
  if (!output->write_image(type, image.pixels, OIIO::AutoStride, row_bytes) || !output->close())
    throw IoError(cat(path, ": cannot write image: ", one_line(output->geterror())));
  write_file_atomic(path, buffer.data(), buffer.size());
#endif
}

}  // namespace vispack

#include "vispack/render/image.h"

#include <png.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"

namespace vispack::render {

Image8 to_rgba8(const ImageF& image) {
  Image8 out(image.width, image.height);
  for (std::size_t i = 0; i < image.rgba.size(); ++i) {
    float v = image.rgba[i];
    if (!(v > 0)) v = 0;
    if (v > 1) v = 1;
    out.rgba[i] = std::uint8_t(std::lround(v * 255.0f));
  }
  return out;
}

double psnr_rgb(const Image8& a, const Image8& b) {
  if (a.width != b.width || a.height != b.height)
    throw std::invalid_argument("psnr_rgb: images differ in size");
  double se = 0;
  std::size_t n = std::size_t(a.width) * a.height;
  for (std::size_t i = 0; i < n; ++i)
    for (int c = 0; c < 3; ++c) {
      double d = double(a.rgba[4 * i + c]) - double(b.rgba[4 * i + c]);
      se += d * d;
    }
  if (se == 0 || n == 0) return std::numeric_limits<double>::infinity();
  double mse = se / double(3 * n);
  return 10.0 * std::log10(255.0 * 255.0 / mse);
}

int max_abs_diff_rgb(const Image8& a, const Image8& b) {
  if (a.width != b.width || a.height != b.height)
    throw std::invalid_argument("max_abs_diff_rgb: images differ in size");
  int m = 0;
  for (std::size_t i = 0; i < a.rgba.size(); ++i)
    if (i % 4 != 3) m = std::max(m, std::abs(int(a.rgba[i]) - int(b.rgba[i])));
  return m;
}

std::int64_t count_non_background(const Image8& image, const std::uint8_t background[3],
                                  int threshold) {
  std::int64_t count = 0;
  std::size_t n = std::size_t(image.width) * image.height;
  for (std::size_t i = 0; i < n; ++i)
    for (int c = 0; c < 3; ++c)
      if (std::abs(int(image.rgba[4 * i + c]) - int(background[c])) > threshold) {
        ++count;
        break;
      }
  return count;
}

namespace {
void append(png_structp png, png_bytep data, png_size_t size) {
  auto* out = static_cast<std::string*>(png_get_io_ptr(png));
  out->append(reinterpret_cast<const char*>(data), size);
}
void flush(png_structp) {}
}  // namespace

void write_png(const std::string& path, const Image8& image, bool keep_alpha) {
  if (image.width <= 0 || image.height <= 0)
    throw IoError(cat(path, ": cannot write an empty image"));
  std::string bytes;
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  if (!png || !info) {
    png_destroy_write_struct(&png, &info);
    throw IoError(cat(path, ": cannot initialise libpng"));
  }
  int channels = keep_alpha ? 4 : 3;
  std::vector<std::uint8_t> row(std::size_t(image.width) * channels);
  if (setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    throw IoError(cat(path, ": PNG encoding failed"));
  }
  png_set_write_fn(png, &bytes, append, flush);
  png_set_IHDR(png, info, png_uint_32(image.width), png_uint_32(image.height), 8,
               keep_alpha ? PNG_COLOR_TYPE_RGBA : PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  for (int y = 0; y < image.height; ++y) {
    for (int x = 0; x < image.width; ++x)
      for (int c = 0; c < channels; ++c)
        row[std::size_t(x) * channels + c] = image.at(x, y)[c];
    png_write_row(png, row.data());
  }
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  write_file_atomic(path, bytes);
}

}  // namespace vispack::render

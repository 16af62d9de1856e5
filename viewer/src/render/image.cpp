#include "vispack/render/image.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/image_io.h"

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

ForegroundDiff diff_foreground(const Image8& a, const Image8& b, const std::uint8_t background[3]) {
  if (a.width != b.width || a.height != b.height)
    throw std::invalid_argument("diff_foreground: images differ in size");
  static const std::uint8_t kBlack[3] = {0, 0, 0};
  const std::uint8_t* bg = background ? background : kBlack;
  ForegroundDiff d;
  double se = 0;
  const std::size_t n = std::size_t(a.width) * a.height;
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint8_t* p = &a.rgba[4 * i];
    const std::uint8_t* q = &b.rgba[4 * i];
    bool lit = false;
    for (int c = 0; c < 3; ++c)
      lit = lit || p[c] != bg[c] || q[c] != bg[c];
    if (!lit) continue;
    ++d.pixels;
    for (int c = 0; c < 3; ++c) {
      const int e = std::abs(int(p[c]) - int(q[c]));
      se += double(e) * e;
      d.max_diff = std::max(d.max_diff, e);
    }
  }
  d.psnr_db = se == 0 ? std::numeric_limits<double>::infinity()
                      : 10.0 * std::log10(255.0 * 255.0 * 3.0 * double(d.pixels) / se);
  return d;
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

void write_png(const std::string& path, const Image8& image, bool keep_alpha) {
  if (image.width <= 0 || image.height <= 0)
    throw IoError(cat(path, ": cannot write an empty image"));
  if (keep_alpha) {
    write_image_file(path, ImageView{image.width, image.height, 4, 8, image.rgba.data(), 0});
    return;
  }
  std::vector<std::uint8_t> rgb(std::size_t(image.width) * image.height * 3);
  for (std::size_t i = 0, n = std::size_t(image.width) * image.height; i < n; ++i)
    for (int c = 0; c < 3; ++c)
      rgb[3 * i + std::size_t(c)] = image.rgba[4 * i + std::size_t(c)];
  write_image_file(path, ImageView{image.width, image.height, 3, 8, rgb.data(), 0});
}

}  // namespace vispack::render

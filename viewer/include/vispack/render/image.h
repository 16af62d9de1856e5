// Images produced by the renderers, their comparison (PSNR) and PNG output.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace vispack::render {

// Float RGBA image, row 0 at the top, 4 floats per pixel.
struct ImageF {
  int width = 0, height = 0;
  std::vector<float> rgba;
  ImageF() = default;
  ImageF(int w, int h) : width(w), height(h), rgba(std::size_t(w) * h * 4, 0.0f) {}
  float* at(int x, int y) { return &rgba[(std::size_t(y) * width + x) * 4]; }
  const float* at(int x, int y) const { return &rgba[(std::size_t(y) * width + x) * 4]; }
};

// 8-bit RGBA image, row 0 at the top.
struct Image8 {
  int width = 0, height = 0;
  std::vector<std::uint8_t> rgba;
  Image8() = default;
  Image8(int w, int h) : width(w), height(h), rgba(std::size_t(w) * h * 4, 0) {}
  const std::uint8_t* at(int x, int y) const { return &rgba[(std::size_t(y) * width + x) * 4]; }
};

// Rounds [0, 1] floats to 8 bits (round to nearest, clamped), as a GL RGBA8 target does.
Image8 to_rgba8(const ImageF& image);

// PSNR in dB over the RGB channels of two same-sized 8-bit images (peak 255); +inf when equal.
// Throws std::invalid_argument if the sizes differ.
double psnr_rgb(const Image8& a, const Image8& b);

// Image comparison over the foreground, the measure of the viewer benchmark (docs/BENCHMARKS.md,
// 'Viewer: bricks paged by view') and of the image tests. A pixel is foreground when its RGB
// differs from `background` in any channel in either image (exactly: no threshold, so a faint haze
// counts); the other pixels are equal in both images and are left out, since over the whole frame
// an identical background inflates the PSNR by 10 log10(frame pixels / foreground pixels). psnr_db
// = 10 log10(255^2 / MSE), the MSE taken over the R, G and B of the foreground pixels (alpha
// ignored); +inf when no foreground pixel differs (including when there is no foreground at all).
struct ForegroundDiff {
  std::int64_t pixels = 0;  // foreground pixels compared
  double psnr_db = 0;       // over their RGB
  int max_diff = 0;         // largest |a - b| of one channel over the whole frame
};
// Throws std::invalid_argument if the sizes differ. `background` defaults to black.
ForegroundDiff diff_foreground(const Image8& a, const Image8& b,
                               const std::uint8_t background[3] = nullptr);

// Largest absolute RGB difference (0..255).
int max_abs_diff_rgb(const Image8& a, const Image8& b);
// Number of pixels whose RGB differs from `background` by more than `threshold` in any channel.
std::int64_t count_non_background(const Image8& image, const std::uint8_t background[3],
                                  int threshold = 2);

// Writes an 8-bit RGBA PNG (alpha dropped when `keep_alpha` is false) atomically.
// Throws IoError naming the path.
void write_png(const std::string& path, const Image8& image, bool keep_alpha = false);

}  // namespace vispack::render

// Image comparison over the foreground (the body): the pixels where either image differs from
// the background. Over the whole frame the identical background inflates the PSNR by
// 10 log10(frame / body), 7..13 dB where the body covers 5..20 % of the frame.
#pragma once

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>

#include "vispack/render/image.h"

namespace vispack::test {

struct BodyDiff {
  std::int64_t body = 0;    // pixels compared (render::diff_foreground's foreground)
  double psnr = 0;          // over those pixels' RGB (+inf when equal)
  int max_diff = 0;         // largest |a - b| of one channel
  std::int64_t over_8 = 0;  // pixels with a channel differing by more than 8
};

// render::diff_foreground (the one definition, shared with the benchmarks) plus the count of
// pixels off by more than 8 in a channel.
inline BodyDiff diff_in_body(const render::Image8& a, const render::Image8& b,
                             const std::uint8_t bg[3] = nullptr) {
  EXPECT_EQ(a.width, b.width);
  EXPECT_EQ(a.height, b.height);
  if (a.width != b.width || a.height != b.height) return {};
  const render::ForegroundDiff f = render::diff_foreground(a, b, bg);
  BodyDiff d{f.pixels, f.psnr_db, f.max_diff, 0};
  for (std::size_t i = 0; i + 3 < a.rgba.size() && i + 3 < b.rgba.size(); i += 4) {
    int worst = 0;
    for (int c = 0; c < 3; ++c)
      worst = std::max(worst, std::abs(int(a.rgba[i + c]) - int(b.rgba[i + c])));
    if (worst > 8) ++d.over_8;
  }
  return d;
}

}  // namespace vispack::test

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
  std::int64_t body = 0;    // pixels compared
  double psnr = 0;          // over those pixels' RGB (99 when equal)
  int max_diff = 0;         // largest |a - b| of one channel
  std::int64_t over_8 = 0;  // pixels with a channel differing by more than 8
};

inline BodyDiff diff_in_body(const render::Image8& a, const render::Image8& b,
                             const std::uint8_t bg[3] = nullptr) {
  static const std::uint8_t black[3] = {0, 0, 0};
  if (!bg) bg = black;
  EXPECT_EQ(a.width, b.width);
  EXPECT_EQ(a.height, b.height);
  BodyDiff d;
  double se = 0;
  for (std::size_t i = 0; i + 3 < a.rgba.size() && i + 3 < b.rgba.size(); i += 4) {
    bool lit = false;
    for (int c = 0; c < 3; ++c)
      lit = lit || a.rgba[i + c] != bg[c] || b.rgba[i + c] != bg[c];
    if (!lit) continue;
    ++d.body;
    int worst = 0;
    for (int c = 0; c < 3; ++c) {
      const int e = std::abs(int(a.rgba[i + c]) - int(b.rgba[i + c]));
      se += double(e) * e;
      worst = std::max(worst, e);
    }
    d.max_diff = std::max(d.max_diff, worst);
    if (worst > 8) ++d.over_8;
  }
  d.psnr = se == 0 ? 99.0 : 10.0 * std::log10(255.0 * 255.0 * 3.0 * double(d.body) / se);
  return d;
}

}  // namespace vispack::test

#include "vispack/render/transfer.h"

#include <algorithm>
#include <cmath>

namespace vispack::render {

const char* mode_name(Mode m) {
  switch (m) {
    case Mode::kColour:
      return "colour";
    case Mode::kCt:
      return "ct";
    case Mode::kMip:
      return "mip";
    case Mode::kAverage:
      return "average";
    case Mode::kIso:
      return "iso";
    case Mode::kLabels:
      return "labels";
    case Mode::kMpr:
      return "mpr";
  }
  return "?";
}

std::optional<Mode> mode_from_name(const std::string& name) {
  for (Mode m : {Mode::kColour, Mode::kCt, Mode::kMip, Mode::kAverage, Mode::kIso, Mode::kLabels,
                 Mode::kMpr})
    if (name == mode_name(m)) return m;
  if (name == "color") return Mode::kColour;
  return std::nullopt;
}

ColourRamp make_ramp(const std::string& name) {
  struct Stop {
    double t, r, g, b;
  };
  std::vector<Stop> stops;
  if (name == "bone")
    stops = {{0, 0, 0, 0}, {0.35, 0.55, 0.2, 0.12}, {0.7, 0.95, 0.85, 0.7}, {1, 1, 1, 1}};
  else if (name == "hot")
    stops = {{0, 0, 0, 0}, {0.4, 0.9, 0.1, 0}, {0.75, 1, 0.9, 0.1}, {1, 1, 1, 1}};
  else
    stops = {{0, 0, 0, 0}, {1, 1, 1, 1}};
  ColourRamp ramp;
  for (int i = 0; i < kRampSize; ++i) {
    double t = double(i) / (kRampSize - 1);
    std::size_t s = 1;
    while (s + 1 < stops.size() && stops[s].t < t)
      ++s;
    const Stop& a = stops[s - 1];
    const Stop& b = stops[s];
    double f = std::clamp((t - a.t) / (b.t - a.t), 0.0, 1.0);
    ramp[i] = {float(a.r + (b.r - a.r) * f), float(a.g + (b.g - a.g) * f),
               float(a.b + (b.b - a.b) * f), 1.0f};
  }
  return ramp;
}

Rgba sample_ramp(const ColourRamp& ramp, double t) {
  if (!(t > 0)) t = 0;  // NaN → 0
  if (t > 1) t = 1;
  double x = t * (kRampSize - 1);
  int i = std::min(int(x), kRampSize - 2);
  float f = float(x - i);
  const Rgba& a = ramp[i];
  const Rgba& b = ramp[i + 1];
  return {a.r + (b.r - a.r) * f, a.g + (b.g - a.g) * f, a.b + (b.b - a.b) * f,
          a.a + (b.a - a.a) * f};
}

std::vector<Rgba> make_label_colours(const std::vector<Label>& labels, double opacity) {
  float alpha = float(std::clamp(std::isfinite(opacity) ? opacity : 0.0, 0.0, 1.0));
  // IDs missing from the table still show (grey), so an incomplete table hides nothing.
  std::vector<Rgba> table(kLabelTableSize, Rgba{0.5f, 0.5f, 0.5f, alpha});
  table[0] = Rgba{0, 0, 0, 0};
  for (const Label& l : labels)
    if (l.id > 0 && l.id < std::uint32_t(kLabelTableSize))
      table[l.id] = {l.colour[0] / 255.0f, l.colour[1] / 255.0f, l.colour[2] / 255.0f, alpha};
  return table;
}

double opacity_correct(double alpha, double ratio) {
  if (!(alpha > 0)) return 0.0;  // also NaN
  if (alpha >= 1) return 1.0;    // no pow of a zero or negative base
  if (!(ratio >= 0)) ratio = std::isnan(ratio) ? 1.0 : 0.0;
  if (std::isinf(ratio)) return 1.0;
  return 1.0 - std::pow(1.0 - alpha, ratio);
}

double window01(double hu, double center, double width) {
  if (!std::isfinite(hu)) return 0.0;
  if (!(width > 0)) return hu >= center ? 1.0 : 0.0;
  double t = (hu - (center - 0.5 * width)) / width;
  return std::clamp(t, 0.0, 1.0);
}

Rgba shade_iso(const Rgba& colour, Vec3 gradient, Vec3 ray_dir) {
  Vec3 view = normalize_or(-ray_dir, Vec3{0, 0, 1});
  Vec3 n = view;
  double g = length(gradient);
  if (g > 1e-6 && std::isfinite(g)) n = -gradient / g;
  double ndl = dot(n, view);
  double diffuse = std::fabs(ndl);
  Vec3 r = n * (2.0 * ndl) - view;
  double spec = std::pow(std::max(dot(r, view), 0.0), 32.0);
  auto ch = [&](float c) {
    return float(std::clamp(c * (0.25 + 0.65 * diffuse) + 0.25 * spec, 0.0, 1.0));
  };
  return {ch(colour.r), ch(colour.g), ch(colour.b), 1.0f};
}

}  // namespace vispack::render

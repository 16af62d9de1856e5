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
    case Mode::kTf2d:
      return "tf2d";
  }
  return "?";
}

std::optional<Mode> mode_from_name(const std::string& name) {
  for (Mode m : {Mode::kColour, Mode::kCt, Mode::kMip, Mode::kAverage, Mode::kIso, Mode::kLabels,
                 Mode::kMpr, Mode::kTf2d})
    if (name == mode_name(m)) return m;
  if (name == "color") return Mode::kColour;
  return std::nullopt;
}

ColourRamp make_ramp(const std::string& name) {
  struct Stop {
    double t, r, g, b;
  };
  // Built once, never assigned (assigning a list to an empty vector trips GCC 12's -Wnonnull).
  static const std::vector<Stop> bone = {
      {0, 0, 0, 0}, {0.35, 0.55, 0.2, 0.12}, {0.7, 0.95, 0.85, 0.7}, {1, 1, 1, 1}};
  static const std::vector<Stop> hot = {
      {0, 0, 0, 0}, {0.4, 0.9, 0.1, 0}, {0.75, 1, 0.9, 0.1}, {1, 1, 1, 1}};
  static const std::vector<Stop> grey = {{0, 0, 0, 0}, {1, 1, 1, 1}};
  const std::vector<Stop>& stops = name == "bone" ? bone : name == "hot" ? hot : grey;
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

namespace vispack::render {

const char* label_shading_name(LabelShading s) {
  switch (s) {
    case LabelShading::kFlat:
      return "flat";
    case LabelShading::kModulated:
      return "modulated";
    case LabelShading::kRamp:
      return "ramp";
  }
  return "?";
}

std::optional<LabelShading> label_shading_from_name(const std::string& name) {
  for (LabelShading s : {LabelShading::kFlat, LabelShading::kModulated, LabelShading::kRamp})
    if (name == label_shading_name(s)) return s;
  return std::nullopt;
}

Rgba shade_label(const Rgba& c, LabelShading shading, double t) {
  if (!(t > 0)) t = 0;
  if (t > 1) t = 1;
  const float f = float(t);
  switch (shading) {
    case LabelShading::kFlat:
      return c;
    case LabelShading::kModulated: {
      const float k = float(kModulatedFloor) + (1.0f - float(kModulatedFloor)) * f;
      return {c.r * k, c.g * k, c.b * k, c.a};
    }
    case LabelShading::kRamp:
      if (f < 0.5f) return {c.r * 2 * f, c.g * 2 * f, c.b * 2 * f, c.a};
      return {c.r + (1 - c.r) * (2 * f - 1), c.g + (1 - c.g) * (2 * f - 1),
              c.b + (1 - c.b) * (2 * f - 1), c.a};
  }
  return c;
}

namespace {
double tf_position(double v, double lo, double hi, int n) {
  double t = hi > lo ? (v - lo) / (hi - lo) : 0.0;
  if (!(t > 0)) t = 0;  // NaN -> 0
  if (t > 1) t = 1;
  return t * (n - 1);
}
}  // namespace

Rgba TransferFunction2D::sample(double hu, double g) const {
  const double x = tf_position(hu, value_min, value_max, kValues);
  const double y = tf_position(g, 0.0, gradient_max, kGradients);
  const int i = std::min(int(x), kValues - 2), j = std::min(int(y), kGradients - 2);
  const float fx = float(x - i), fy = float(y - j);
  auto at = [&](int a, int b) { return table[std::size_t(b) * kValues + std::size_t(a)]; };
  Rgba c00 = at(i, j), c10 = at(i + 1, j), c01 = at(i, j + 1), c11 = at(i + 1, j + 1);
  auto mix = [](const Rgba& a, const Rgba& b, float f) {
    return Rgba{a.r + (b.r - a.r) * f, a.g + (b.g - a.g) * f, a.b + (b.b - a.b) * f,
                a.a + (b.a - a.a) * f};
  };
  return mix(mix(c00, c10, fx), mix(c01, c11, fx), fy);
}

bool TransferFunction2D::any_opacity(double hu_lo, double hu_hi) const {
  const double x0 = tf_position(hu_lo, value_min, value_max, kValues);
  const double x1 = tf_position(hu_hi, value_min, value_max, kValues);
  const int i0 = std::max(0, int(std::floor(x0))), i1 = std::min(kValues - 1, int(std::ceil(x1)));
  for (int j = 0; j < kGradients; ++j)
    for (int i = i0; i <= i1; ++i)
      if (table[std::size_t(j) * kValues + std::size_t(i)].a > 0) return true;
  return false;
}

TransferFunction2D make_tf2d(const std::vector<Tf2dWidget>& widgets, double value_min,
                             double value_max, double gradient_max) {
  TransferFunction2D tf;
  tf.value_min = value_min;
  tf.value_max = value_max > value_min ? value_max : value_min + 1;
  tf.gradient_max = gradient_max > 0 ? gradient_max : 1;
  for (int j = 0; j < TransferFunction2D::kGradients; ++j)
    for (int i = 0; i < TransferFunction2D::kValues; ++i) {
      const double v =
          tf.value_min + (tf.value_max - tf.value_min) * i / (TransferFunction2D::kValues - 1);
      const double g = tf.gradient_max * j / (TransferFunction2D::kGradients - 1);
      Rgba best;
      for (const Tf2dWidget& w : widgets) {
        if (!(w.value_hi > w.value_lo) || g < w.gradient_lo || g > w.gradient_hi) continue;
        const double c = 0.5 * (w.value_lo + w.value_hi), h = 0.5 * (w.value_hi - w.value_lo);
        double tent = std::max(0.0, 1.0 - std::fabs(v - c) / h);
        if (w.gradient_weighted)
          tent *= w.gradient_hi > w.gradient_lo
                      ? (g - w.gradient_lo) / (w.gradient_hi - w.gradient_lo)
                      : 1.0;
        const float a = float(std::clamp(double(w.colour.a), 0.0, 1.0) * tent);
        if (a > best.a) best = {w.colour.r, w.colour.g, w.colour.b, a};
      }
      tf.table[std::size_t(j) * TransferFunction2D::kValues + std::size_t(i)] = best;
    }
  return tf;
}

}  // namespace vispack::render

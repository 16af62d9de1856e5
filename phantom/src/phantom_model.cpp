#include "phantom_model.h"

#include <algorithm>
#include <cmath>
#include <iterator>

#include "vispack/common/math_constants.h"

namespace vispack::phantom::detail {
namespace {

// Body size along a tapering stack: sin(π t)^0.3, exactly 0 near both ends (not a speck).
double taper(double t) {
  const double v = std::pow(std::max(0.0, std::sin(kPi * t)), 0.3);
  return v < 1e-3 ? 0.0 : v;
}

double smoothstep(double e0, double e1, double x) {
  const double t = std::clamp((x - e0) / (e1 - e0), 0.0, 1.0);
  return t * t * (3.0 - 2.0 * t);
}

// Coverage of a shape with signed distance `sdf` over an edge of width `w` (1 inside, 0 outside).
inline float cover(double sdf, double w) {
  return static_cast<float>(std::clamp(0.5 - sdf / w, 0.0, 1.0));
}

constexpr double kFar = 1e9;

// Approximate signed distance to an ellipse (first order: (r − 1)/|∇r|, exact on the boundary).
// Points clearly outside the bounding box (by more than `margin`) return kFar cheaply.
inline double ellipse_sdf(double x, double y, double cx, double cy, double a, double b,
                          double margin) {
  if (a <= 1e-6 || b <= 1e-6) return kFar;
  const double dx = x - cx, dy = y - cy;
  if (std::fabs(dx) > a + margin || std::fabs(dy) > b + margin) return kFar;
  const double ux = dx / a, uy = dy / b;
  const double r = std::sqrt(ux * ux + uy * uy);
  if (r < 1e-12) return -std::min(a, b);
  const double g = std::sqrt(ux * ux / (a * a) + uy * uy / (b * b)) / r;
  return (r - 1.0) / g;
}

// Ellipse with two lobes (3-fold and 2-fold) of fixed amplitude, phases from the slice.
constexpr double kLobe3 = 0.035, kLobe2 = 0.02;
inline double lobed_sdf(double x, double y, double a, double b, const double* lobes) {
  if (a <= 1e-6 || b <= 1e-6) return kFar;  // a layer tapered away
  const double ux = x / a, uy = y / b;
  const double r = std::sqrt(ux * ux + uy * uy);
  if (r < 1e-12) return -std::min(a, b);
  const double c = ux / r, s = uy / r;
  const double cos3 = 4 * c * c * c - 3 * c, sin3 = 3 * s - 4 * s * s * s;
  const double cos2 = c * c - s * s, sin2 = 2 * s * c;
  // lobes = {cos φ3, sin φ3, cos φ2, sin φ2} of the slice's lobe phases.
  const double eps =
      kLobe3 * (cos3 * lobes[0] + sin3 * lobes[1]) + kLobe2 * (cos2 * lobes[2] + sin2 * lobes[3]);
  const double g = std::sqrt(ux * ux / (a * a) + uy * uy / (b * b)) / r;
  return (r - (1.0 + eps)) / g;
}

// Anatomy::limbs: the torso's size along the stack (relative to the classic body): the head
// tapering from nothing (t < 0.10), the neck widening into the shoulders, the torso, and the
// pelvis vanishing into the legs (0.62..0.70).
constexpr double kMaleTorso = 0.8, kMaleHead = 0.42;
// The table's top edge (frame units below the centre): the torso's back presses on it where its
// lobes reach that far.
constexpr double kMaleTableTop = 0.50;
double male_torso(double t) {
  if (t < 0.10) return kMaleHead * taper(std::min(0.5, t / 0.12));
  if (t < 0.62) return kMaleHead + (kMaleTorso - kMaleHead) * smoothstep(0.10, 0.15, t);
  return kMaleTorso * (1.0 - smoothstep(0.62, 0.70, t));
}

// Places a limb of semi-axes (a, b) at height y beside the torso on side ±1 so that its nearest
// point lies `gap` (normalised units) from the torso's outline (lobed_sdf, first order).
double beside_torso(const SliceParams& s, double side, double y, double a, double b, double gap) {
  double x = side * (s.a + gap + a);
  for (int iter = 0; iter < 6; ++iter) {
    double nearest = kFar;
    for (int i = 0; i < 48; ++i) {
      const double phi = 2 * kPi * i / 48.0;
      nearest = std::min(nearest, lobed_sdf(x + a * std::cos(phi), y + b * std::sin(phi), s.a, s.b,
                                            s.lobes.data()));
    }
    x += side * (gap - nearest);
  }
  return x;
}

// Anatomy::limbs: the arms, legs, feet and toes of slice parameter t (normalised units; `px` is
// one output pixel, `scale` the frame height relative to 1216 px).
void lay_out_limbs(SliceParams& s, double t, double px, double scale) {
  s.limb_count = 0;
  auto add = [&](double x, double y, double a, double b, double bone) {
    if (a * b <= 0 || s.limb_count >= kMaxLimbs) return;
    s.limbs[std::size_t(s.limb_count++)] = {x, y, a, b, bone};
  };
  // Arms beside the torso from the shoulders (t 0.14) to the hands (0.56): upper arm, forearm,
  // then a flat hand. Each gap wanders between 2 and 40 px (at 1216 px height), the two sides out
  // of phase; the right arm rests on the table (its lowest point 1 px into the table's top) for
  // t in 0.30..0.40 and lies 0.03 above it before 0.22 and after 0.48, moving smoothly between
  // (an arm does not jump from one slice to the next).
  if (t >= 0.14 && t < 0.56) {
    const double u = (t - 0.14) / 0.42;
    const double grow = smoothstep(0.14, 0.17, t) * (1.0 - smoothstep(0.53, 0.56, t));
    const double hand = smoothstep(0.46, 0.50, t);
    const double a = (0.15 - 0.04 * u) * (1 - hand) + 0.05 * hand, b = (0.16 - 0.03 * u);
    for (int side : {-1, 1}) {
      const double wave = 0.5 + 0.5 * std::sin(2 * kPi * (1.5 * u + (side > 0 ? 0.0 : 0.4)));
      const double gap = std::max(2.0, (2.0 + 38.0 * wave) * scale) * px;
      const double rest = smoothstep(0.22, 0.30, t) * (1.0 - smoothstep(0.40, 0.48, t));
      const double y = side > 0 ? s.table_top - s.y0 - b * grow - 0.03 + rest * (0.03 + px) : 0.12;
      add(beside_torso(s, side, y, a * grow, b * grow, gap), y, a * grow, b * grow,
          hand > 0.5 ? 0.0 : 0.25);
    }
  }
  // Two legs from the pelvis (0.64) to the ankles (0.93), parting as the torso vanishes; the
  // thighs taper to the calves.
  if (t >= 0.64 && t < 0.93) {
    const double part = smoothstep(0.64, 0.76, t), u = (t - 0.64) / 0.29;
    const double a = 0.30 - 0.13 * u, b = 0.32 - 0.12 * u;
    const double grow = smoothstep(0.64, 0.68, t);
    for (int side : {-1, 1})
      add(side * (0.20 + 0.16 * part), 0.05, a * grow, b * grow, 0.25);
  }
  // Feet (0.93..0.975): long ellipses reaching forward (−y); then five toes per foot tapering
  // to nothing at the end of the stack.
  if (t >= 0.93 && t < 0.975) {
    for (int side : {-1, 1})
      add(side * 0.36, -0.05, 0.13, 0.27, 0.2);
  } else if (t >= 0.975) {
    const double r = 0.05 * taper(std::min(0.5, (1.0 - t) / 0.05));
    for (int side : {-1, 1})
      for (int i = 0; i < 5; ++i)
        add(side * (0.36 + 0.13 * (i - 2) * 0.9), -0.25 + 0.02 * std::abs(i - 2),
            r * (i == 2 ? 1.2 : 1.0), r * (i == 2 ? 1.2 : 1.0), 0.0);
  }
}

struct Tissue {
  float rgb[3];
  float texture;  // relative amplitude of the texture
  float hu;
  float hu_texture;
};
// Cryosection-like colours (pinks, reds, creamy fat, white bone) and CT numbers.
const Tissue kTissues[kLabelCount] = {
    {{36, 64, 148}, 0.05f, -1000, 0},    // 0: gel (RGB) / air (CT)
    {{196, 150, 128}, 0.06f, 30, 6},     // skin
    {{236, 212, 156}, 0.07f, -100, 10},  // fat
    {{152, 52, 48}, 0.14f, 45, 8},       // muscle
    {{232, 226, 208}, 0.05f, 900, 150},  // bone
    {{182, 102, 112}, 0.25f, -800, 40},  // lungs (air-filled)
    {{118, 34, 42}, 0.10f, 40, 8},       // heart
    {{112, 48, 36}, 0.08f, 60, 8},       // liver
    {{138, 62, 54}, 0.10f, 35, 8},       // kidneys
    {{206, 160, 142}, 0.10f, 20, 8},     // connective tissue
};
constexpr float kTube[3] = {72, 176, 84};
constexpr float kHolderHu = 200.f;

const LabelInfo kLabelInfo[kLabelCount] = {
    {"background", {0, 0, 0}},  {"skin", {230, 180, 140}},
    {"fat", {255, 240, 80}},    {"muscle", {200, 40, 40}},
    {"bone", {245, 245, 245}},  {"lungs", {255, 110, 200}},
    {"heart", {140, 0, 90}},    {"liver", {120, 70, 20}},
    {"kidneys", {0, 160, 160}}, {"connective tissue", {120, 120, 255}},
};

// Blends `into` toward tissue `label` (with texture `n`) by coverage c.
struct Accum {
  float rgb[3];
  float hu;
  void mix(const Tissue& t, float c, float n, float m, bool want_rgb, bool want_ct,
           const float* override_rgb = nullptr) {
    if (c <= 0.f) return;
    if (want_rgb) {
      const float* base = override_rgb ? override_rgb : t.rgb;
      const float k = 1.f + t.texture * n;
      // A slow hue wobble (warmer / cooler) on top of the brightness texture.
      const float hue[3] = {6.f * m, -3.f * m, -6.f * m};
      for (int i = 0; i < 3; ++i)
        rgb[i] += c * (base[i] * k + hue[i] - rgb[i]);
    }
    if (want_ct) hu += c * (t.hu + t.hu_texture * n - hu);
  }
  // Lays `inner` (a part's tissues) over this with coverage c.
  void over(const Accum& inner, float c) {
    for (int i = 0; i < 3; ++i)
      rgb[i] += c * (inner.rgb[i] - rgb[i]);
    hu += c * (inner.hu - hu);
  }
};

}  // namespace

// ---------------------------------------------------------------------------------------------
Random::Random(std::uint64_t seed) : engine_(mix64(seed)) {}
std::uint64_t Random::next() {
  return engine_();
}
double Random::uniform() {
  return double(engine_() >> 11) * (1.0 / 9007199254740992.0);
}
double Random::uniform(double lo, double hi) {
  return lo + (hi - lo) * uniform();
}
double Random::normal(double sigma) {
  if (has_spare_) {
    has_spare_ = false;
    return spare_ * sigma;
  }
  double u1 = uniform();
  while (u1 <= 0.0)
    u1 = uniform();
  const double u2 = uniform();
  const double r = std::sqrt(-2.0 * std::log(u1));
  spare_ = r * std::sin(2 * kPi * u2);
  has_spare_ = true;
  return r * std::cos(2 * kPi * u2) * sigma;
}

void Random::normal4(const GaussianTable& table, float out[4]) {
  const std::uint64_t bits = engine_();
  for (int i = 0; i < 4; ++i)
    out[i] = table[(bits >> (16 * i)) & 0xffff];
}

GaussianTable::GaussianTable() : values_(65536) {
  // Newton's method on Φ(x) = erfc(−x/√2)/2 from a logistic first guess, kept inside a bracket
  // that shrinks with every evaluation (bisection when a step would leave it): plain Newton
  // diverges in the far tails (the pdf underflows) and used to leave NaN there, which
  // rounded to black specks in the slices.
  for (int i = 0; i < 65536; ++i) {
    const double p = (i + 0.5) / 65536.0;
    double lo = -12.0, hi = 12.0;
    double x = std::log(p / (1 - p)) / 1.702;
    for (int iter = 0; iter < 200; ++iter) {
      const double cdf = 0.5 * std::erfc(-x / std::sqrt(2.0));
      if (cdf < p)
        lo = x;
      else
        hi = x;
      const double pdf = std::exp(-0.5 * x * x) / std::sqrt(2 * kPi);
      double next = x - (cdf - p) / pdf;
      if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
      const double step = std::fabs(next - x);
      x = next;
      if (step < 1e-12 || hi - lo < 1e-12) break;
    }
    values_[std::size_t(i)] = static_cast<float>(x);
  }
}

const LabelInfo& label_info(int label) {
  return kLabelInfo[label];
}

// ---------------------------------------------------------------------------------------------
NoiseLayer::NoiseLayer(std::uint64_t key, double scale_px, double scale_slices, double slice,
                       double x_lo, double x_hi, double y_lo, double y_hi)
    : key_(key), inv_scale_(1.0 / scale_px) {
  const double z = slice / scale_slices;
  iz_ = static_cast<std::int64_t>(std::floor(z));
  const double f = z - double(iz_);
  fz_ = static_cast<float>(f * f * (3 - 2 * f));
  x0_ = static_cast<std::int64_t>(std::floor(x_lo * inv_scale_)) - 1;
  y0_ = static_cast<std::int64_t>(std::floor(y_lo * inv_scale_)) - 1;
  nx_ = static_cast<std::int64_t>(std::floor(x_hi * inv_scale_)) + 3 - x0_;
  ny_ = static_cast<std::int64_t>(std::floor(y_hi * inv_scale_)) + 3 - y0_;
  cache_.resize(std::size_t(nx_ * ny_));
  for (std::int64_t j = 0; j < ny_; ++j)
    for (std::int64_t i = 0; i < nx_; ++i)
      cache_[std::size_t(j * nx_ + i)] = compute(x0_ + i, y0_ + j);
}

float NoiseLayer::compute(std::int64_t ix, std::int64_t iy) const {
  auto value = [&](std::int64_t iz) {
    const std::uint64_t h = mix64(key_ ^ mix64(std::uint64_t(ix) * 0x8cb92ba72f3d8dd7ull +
                                               std::uint64_t(iy) * 0xd6e8feb86659fd93ull +
                                               std::uint64_t(iz) * 0xa0761d6478bd642full));
    return float(double(h >> 40) * (2.0 / 16777216.0) - 1.0);
  };
  const float v0 = value(iz_), v1 = value(iz_ + 1);
  return v0 + (v1 - v0) * fz_;
}

float NoiseLayer::lattice(std::int64_t ix, std::int64_t iy) const {
  const std::int64_t i = ix - x0_, j = iy - y0_;
  if (i >= 0 && j >= 0 && i < nx_ && j < ny_) return cache_[std::size_t(j * nx_ + i)];
  return compute(ix, iy);
}

float NoiseLayer::at(double x, double y) const {
  const double u = x * inv_scale_, v = y * inv_scale_;
  const double fu = std::floor(u), fv = std::floor(v);
  const auto ix = static_cast<std::int64_t>(fu), iy = static_cast<std::int64_t>(fv);
  double s = u - fu, t = v - fv;
  s = s * s * (3 - 2 * s);
  t = t * t * (3 - 2 * t);
  const float a = lattice(ix, iy), b = lattice(ix + 1, iy);
  const float c = lattice(ix, iy + 1), d = lattice(ix + 1, iy + 1);
  const double top = a + (b - a) * s, bottom = c + (d - c) * s;
  return static_cast<float>(top + (bottom - top) * t);
}

// ---------------------------------------------------------------------------------------------
Model::Model(int width, int height, int slices, std::uint64_t seed, const Anatomy& anatomy)
    : width_(width), height_(height), slices_(slices), seed_(seed), anatomy_(anatomy) {
  cx_ = (width - 1) * 0.5;
  cy_ = (height - 1) * 0.5;
  half_ = height * 0.5;
}

double Model::body_max_a(const Anatomy& anatomy) {
  // The torso with an arm at the largest gap (40 px at 1216 px height: 0.066) on each side.
  if (anatomy.limbs)
    return (kBodyA * kMaleTorso * 1.05 * (1 + kLobe3 + kLobe2) + 0.075 + 2 * 0.15) *
           anatomy.body_scale;
  return kBodyA * 1.05 * (1 + kLobe3 + kLobe2) * anatomy.body_scale +
         0.5 * std::fabs(anatomy.shift_x);
}
double Model::body_max_b(const Anatomy& anatomy) {
  if (anatomy.limbs) return kMaleTableTop * anatomy.body_scale + 0.05;
  return kBodyB * 1.04 * (1 + kLobe3 + kLobe2) * anatomy.body_scale +
         0.5 * std::fabs(anatomy.shift_y);
}

SliceParams Model::slice(int k) const {
  SliceParams s;
  s.slice = k;
  // Anatomy changes per slice, not per fraction of the stack: a short stack (a few `vhp`
  // slices) sees a slowly changing body, as a real one would, instead of the whole anatomy
  // squeezed into a few slices (which registration would read as motion). Stacks of 24 slices
  // or more (tiny, small, medium) span the whole model.
  // A varying anatomy always spans the whole model over the stack, whatever its length.
  const int span = anatomy_.varying ? std::max(slices_ - 1, 1) : std::max(slices_ - 1, 23);
  const double t = slices_ > 1 ? std::min(1.0, double(k) / double(span)) : 0.0;
  s.t = t;
  // Smooth changes with z (the same for every seed: the seed moves the texture and the drift).
  const double size = anatomy_.body_scale * (anatomy_.limbs   ? male_torso(t)
                                             : anatomy_.taper ? taper(t)
                                                              : 1.0);
  s.a = size * kBodyA * (1 + 0.05 * std::sin(2 * kPi * (0.7 * t + 0.1)));
  s.b = size * kBodyB * (1 + 0.04 * std::sin(2 * kPi * (0.5 * t + 0.3)));
  s.x0 = anatomy_.shift_x * (t - 0.5);
  s.y0 = anatomy_.shift_y * (t - 0.5);
  if (anatomy_.varying) {
    // Organs wander inside the body (each on its own slow path).
    for (int i = 0; i < 6; ++i)
      s.organ_shift[std::size_t(i)] = {0.08 * std::sin(2 * kPi * t + 1.3 * i),
                                       0.05 * std::cos(2 * kPi * 0.7 * t + 0.9 * i)};
  }
  // The outline changes with z by scaling about the body centre only, never by turning: an
  // in-plane rotation of the anatomy along the stack is indistinguishable from drift for any
  // slice-to-slice registration, so it would make the truth ambiguous (real bodies do not twist
  // by tens of degrees along a block either). Lobe phases and rib angles are therefore fixed.
  const double lobe3 = 0.6, lobe2 = 2.0;
  s.lobes = {std::cos(lobe3), std::sin(lobe3), std::cos(lobe2), std::sin(lobe2)};
  if (anatomy_.limbs) {
    s.table_top = kMaleTableTop * anatomy_.body_scale;
    lay_out_limbs(s, t, 1.0 / half_, height_ / 1216.0);
  }
  s.fat_x = 0.07 + 0.015 * std::sin(2 * kPi * t);
  s.fat_y = 0.09 + 0.015 * std::cos(2 * kPi * t);
  s.lung = 1 - 0.55 * smoothstep(0.35, 1.0, t);
  s.heart = 1 - smoothstep(0.5, 0.8, t);
  s.liver = smoothstep(0.25, 0.65, t);
  s.kidney = smoothstep(0.55, 0.85, t);
  s.rib = 1 - smoothstep(0.7, 0.9, t);
  s.notch = 0.75 + 0.25 * std::sin(kPi * t);
  const double rib_shift = 0.0;
  const double rib_angles[6] = {-160, -105, -60, -20, 160, 20};
  for (int i = 0; i < 6; ++i) {
    const double phi = rib_angles[i] * kPi / 180.0 + rib_shift;
    s.ribs[i] = {0.695 * std::cos(phi), 0.405 * std::sin(phi)};
  }
  // Texture lattices cover the frame with a margin for drifted sampling (outside: computed).
  const double pad = 0.25 * std::max(width_, height_) + 32;
  const double x_lo = -pad, x_hi = width_ + pad, y_lo = -pad, y_hi = height_ + pad;
  const double scales[4][2] = {{24, 10}, {9, 6}, {4, 4}, {2.2, 3}};
  // A varying anatomy draws a fresh texture lattice every slice (z scale 1, sampled at integer
  // slices): its texture never repeats from one slice to the next.
  for (int o = 0; o < 4; ++o) {
    const double z_scale = anatomy_.varying ? 1.0 : scales[o][1];
    s.texture[o] =
        NoiseLayer(mix64(seed_ * 4 + o + 1), scales[o][0], z_scale, k, x_lo, x_hi, y_lo, y_hi);
  }
  s.marbling = NoiseLayer(mix64(seed_ * 4 + 101), 14, anatomy_.varying ? 1.0 : 8.0, k, x_lo, x_hi,
                          y_lo, y_hi);
  return s;
}

namespace {

// Where Model::eval samples: frame coordinates (Xf, Yf), body coordinates (X, Y; centre at the
// body's x0, y0) and body-relative ones (Xr, Yr), the edge width w, the texture fields n and m,
// what is wanted, and `resolvable` (a shape of semi-axes a, b is at least one output pixel).
struct EvalPoint {
  double Xf, Yf, X, Y, Xr, Yr, w;
  float n, m;
  bool want_rgb, want_ct;
  double px_x, px_y;  // output pixels per body unit
  bool resolvable(double a, double b) const { return a * px_x >= 1.0 && b * px_y >= 1.0; }
};

// A limb's nested layers (skin, fat, muscle, bone, as in the torso) mixed into `t` (zeroed by
// the caller); `half`: pixels per normalised unit. Returns the label at the point.
std::uint16_t limb_layers(const Limb& l, const EvalPoint& p, double half, Accum& t) {
  const double X = p.X, Y = p.Y, w = p.w;
  const float n = p.n, m = p.m;
  const bool want_rgb = p.want_rgb, want_ct = p.want_ct;
  auto resolved = [&](double a, double b) { return a * half >= 1.0 && b * half >= 1.0; };
  t.mix(kTissues[kSkin], 1.f, n, m, want_rgb, want_ct);
  std::uint16_t label = kSkin;
  const double skin = 0.018, fat_t = 0.18 * std::min(l.a, l.b);
  if (resolved(l.a - skin, l.b - skin)) {
    const double fat = ellipse_sdf(X, Y, l.x, l.y, l.a - skin, l.b - skin, w);
    if (fat < w) {
      t.mix(kTissues[kFat], cover(fat, w), n, m, want_rgb, want_ct);
      if (fat < 0) label = kFat;
      const double ma = l.a - skin - fat_t, mb = l.b - skin - fat_t;
      const double mus = resolved(ma, mb) ? ellipse_sdf(X, Y, l.x, l.y, ma, mb, w) : kFar;
      if (mus < w) {
        t.mix(kTissues[kMuscle], cover(mus, w), n, m, want_rgb, want_ct);
        if (mus < 0) label = kMuscle;
        const double r = l.bone * std::min(l.a, l.b);
        const double bone =
            l.bone > 0 && resolved(r, r) ? ellipse_sdf(X, Y, l.x, l.y, r, r, w) : kFar;
        if (bone < w) {
          t.mix(kTissues[kBone], cover(bone, w), n, m, want_rgb, want_ct);
          if (bone < 0) label = kBone;
        }
      }
    }
  }
  return label;
}

// The torso's nested layers from the outside in (skin, fat, muscle with marbling, the cavity
// and its organs, the bones) mixed into `t` (zeroed by the caller). Returns the label.
std::uint16_t torso_layers(const SliceParams& s, const EvalPoint& p, Accum& t) {
  const double X = p.X, Y = p.Y, Xr = p.Xr, Yr = p.Yr, w = p.w;
  const float n = p.n, m = p.m;
  const bool want_rgb = p.want_rgb, want_ct = p.want_ct;
  auto resolvable = [&](double a, double b) { return p.resolvable(a, b); };
  // Nested layers from the outside in; each mixes its colour over what is outside it.
  t.mix(kTissues[kSkin], 1.f, n, m, want_rgb, want_ct);
  std::uint16_t label = kSkin;
  const double ts = 0.035;
  const double fat = lobed_sdf(X, Y, s.a - ts, s.b - ts, s.lobes.data());
  if (fat < w) {
    t.mix(kTissues[kFat], cover(fat, w), n, m, want_rgb, want_ct);
    if (fat < 0) label = kFat;
    const double mus = lobed_sdf(X, Y, s.a - ts - s.fat_x, s.b - ts - s.fat_y, s.lobes.data());
    if (mus < w) {
      // Muscle with fat marbling where the slow field is high.
      float marbled[3];
      const float mf = 0.55f * static_cast<float>(smoothstep(0.35, 0.75, m));
      for (int i = 0; i < 3; ++i)
        marbled[i] =
            kTissues[kMuscle].rgb[i] + mf * (kTissues[kFat].rgb[i] - kTissues[kMuscle].rgb[i]);
      t.mix(kTissues[kMuscle], cover(mus, w), n, m, want_rgb, want_ct, marbled);
      if (mus < 0) label = kMuscle;
      const double cav = ellipse_sdf(Xr, Yr, 0, 0, 0.645, 0.355, w);
      if (cav < w) {
        t.mix(kTissues[kConnective], cover(cav, w), n, m, want_rgb, want_ct);
        if (cav < 0) label = kConnective;
        struct Organ {
          double cx, cy, a, b;
          std::uint16_t label;
        };
        const Organ organs[] = {
            {-0.33, -0.04, 0.24 * s.lung, 0.25 * s.lung, kLungs},
            {0.33, -0.04, 0.24 * s.lung, 0.25 * s.lung, kLungs},
            {-0.18, 0.08, 0.36 * s.liver, 0.22 * s.liver, kLiver},
            {-0.30, 0.22, 0.09 * s.kidney, 0.065 * s.kidney, kKidneys},
            {0.30, 0.22, 0.09 * s.kidney, 0.065 * s.kidney, kKidneys},
            {0.06, -0.10, 0.17 * s.heart, 0.15 * s.heart, kHeart},
        };
        for (std::size_t i = 0; i < std::size(organs); ++i) {
          const Organ& o = organs[i];
          if (!resolvable(o.a, o.b)) continue;
          const double d = ellipse_sdf(Xr, Yr, o.cx + s.organ_shift[i][0],
                                       o.cy + s.organ_shift[i][1], o.a, o.b, w);
          if (d >= w) continue;
          t.mix(kTissues[o.label], cover(d, w), n, m, want_rgb, want_ct);
          if (d < 0) label = o.label;
        }
      }
      // Bones: spine, sternum, ribs in the muscle ring (drawn over everything inside).
      double bone = ellipse_sdf(Xr, Yr, 0, 0.36, 0.075, 0.075, w);
      bone = std::min(bone, ellipse_sdf(Xr, Yr, 0, -0.405, 0.08, 0.03, w));
      if (s.rib > 1e-3 && resolvable(0.04 * s.rib, 0.04 * s.rib)) {
        const double r = 0.04 * s.rib;
        for (const auto& centre : s.ribs) {
          bone = std::min(bone, ellipse_sdf(Xr, Yr, centre[0], centre[1], r, r, w));
        }
      }
      if (bone < w) {
        t.mix(kTissues[kBone], cover(bone, w), n, m, want_rgb, want_ct);
        if (bone < 0) label = kBone;
      }
    }
  }
  return label;
}

// Outside the body at `p` (`outline`: the signed distance to the body's outline): gel (RGB) with
// the fiducial tubes and tissue showing through near the edge; air (CT) with the holder or, for
// Anatomy::limbs, the table at `table_top`. `half`: pixels per normalised unit.
Accum outside_layer(const EvalPoint& p, double outline, const Anatomy& anatomy, double half,
                    double table_top) {
  const double Xf = p.Xf, Yf = p.Yf, w = p.w;
  const float n = p.n;
  const bool want_rgb = p.want_rgb, want_ct = p.want_ct;
  Accum acc{{0, 0, 0}, -1000.f};
  if (want_rgb) {
    const Tissue& gel = kTissues[0];
    const float k = 1.f + gel.texture * n;
    for (int i = 0; i < 3; ++i)
      acc.rgb[i] = gel.rgb[i] * k;
    if (outline > 0) {
      const float through = 0.35f * static_cast<float>(std::exp(-outline / 0.04));
      for (int i = 0; i < 3; ++i)
        acc.rgb[i] += through * (0.8f * kTissues[kSkin].rgb[i] - acc.rgb[i]);
    }
    const double tube1 = ellipse_sdf(Xf, Yf, -1.08, -0.70, 0.08, 0.08, w);
    const double tube2 = ellipse_sdf(Xf, Yf, 1.08, 0.66, 0.08, 0.08, w);
    const float c = std::max(cover(tube1, w), cover(tube2, w));
    if (c > 0 && anatomy.fiducials) {
      Tissue tube{{kTube[0], kTube[1], kTube[2]}, 0.04f, -1000, 0};
      acc.mix(tube, c, n, 0.f, true, false);
    }
  }
  if (want_ct && anatomy.limbs) {
    // The table: a bar table_px thick under the body, across the whole field of view.
    const double top = table_top, thick = anatomy.table_px / half;
    const double table = std::max(top - Yf, Yf - (top + thick));
    acc.hu = -1000.f + cover(table, w) * (kHolderHu + 1000.f);
  } else if (want_ct) {
    const double ga = Model::body_max_a(anatomy) + 0.10, gb = Model::body_max_b(anatomy) + 0.10;
    const double inner = ellipse_sdf(Xf, Yf, 0, 0, ga, gb, 1e9);
    const double outer = ellipse_sdf(Xf, Yf, 0, 0, ga + 0.08, gb + 0.08, 1e9);
    const double holder = std::max({-inner, outer, 0.15 - Yf});
    acc.hu = -1000.f + cover(holder, w) * (kHolderHu + 1000.f);
  }

  return acc;
}

}  // namespace

void Model::eval(const SliceParams& s, double x, double y, double edge_px, bool want_rgb,
                 bool want_ct, Sample& out) const {
  // Frame coordinates (fiducial tubes, CT holder) and body coordinates (centre at x0, y0).
  const double Xf = (x - cx_) / half_, Yf = (y - cy_) / half_;
  const double X = Xf - s.x0, Y = Yf - s.y0;
  const double w = edge_px / half_;  // edge width, normalised units
  // Interior shapes live in body-relative coordinates so they follow the outline's size.
  const double Xr = s.a > 1e-6 ? X * kBodyA / s.a : kFar, Yr = s.b > 1e-6 ? Y * kBodyB / s.b : kFar;
  // Interior shapes (organs, ribs) growing from or shrinking to nothing are left out while a
  // semi-axis is under one output pixel: a sub-pixel speck would appear on one sampling grid and
  // not on another (the truth grid vs a drifted slice), which no resampling can reproduce.
  const double px_x = half_ * s.a / kBodyA, px_y = half_ * s.b / kBodyB;  // px per body unit

  // Texture: smooth brightness (4 octaves) and a slow second field.
  float n = 0.f, m = 0.f;
  if (want_rgb || want_ct) {
    if (want_rgb) {
      n = 0.5f * s.texture[0].at(x, y) + 0.28f * s.texture[1].at(x, y) +
          0.14f * s.texture[2].at(x, y) + 0.08f * s.texture[3].at(x, y);
      m = s.marbling.at(x, y);
    } else {
      n = s.texture[0].at(x, y);  // CT: the coarse octave only (its pixels are larger)
    }
  }

  const EvalPoint point{Xf, Yf, X, Y, Xr, Yr, w, n, m, want_rgb, want_ct, px_x, px_y};
  const double body = lobed_sdf(X, Y, s.a, s.b, s.lobes.data());
  const double notch = ellipse_sdf(Xr, Yr, -0.45, -0.50, 0.065, 0.17 * s.notch, w);
  const double eff = std::max(body, -notch);  // body minus the gel-filled notch
  // Anatomy::limbs: the nearest limb (arm, leg, foot, toe) and the outline of all parts.
  double limb = kFar;
  int nearest = -1;
  for (int i = 0; i < s.limb_count; ++i) {
    const Limb& l = s.limbs[std::size_t(i)];
    const double d = ellipse_sdf(X, Y, l.x, l.y, l.a, l.b, w);
    if (d < limb) limb = d, nearest = i;
  }
  const double outline = std::min(eff, limb);
  out.body = outline < 0;

  Accum acc = outside_layer(point, outline, anatomy_, half_, s.table_top);

  std::uint16_t label = 0;
  if (nearest >= 0 && limb < w && limb < eff) {
    Accum t = acc;
    t.rgb[0] = t.rgb[1] = t.rgb[2] = 0;
    t.hu = 0;
    label = limb_layers(s.limbs[std::size_t(nearest)], point, half_, t);
    acc.over(t, cover(limb, w));
  } else if (eff < w) {  // anywhere near or inside the body
    Accum t = acc;
    t.rgb[0] = t.rgb[1] = t.rgb[2] = 0;
    t.hu = 0;
    label = torso_layers(s, point, t);
    acc.over(t, cover(eff, w));
  }
  out.label = out.body ? label : 0;
  for (int i = 0; i < 3; ++i)
    out.rgb[i] = acc.rgb[i];
  out.hu = acc.hu;
}

}  // namespace vispack::phantom::detail

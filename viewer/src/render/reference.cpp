#include "vispack/render/reference.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "vispack/common/parallel.h"

namespace vispack::render {

void premultiply_rgba8(const std::uint8_t* in, std::uint8_t* out, std::int64_t voxels) {
  for (std::int64_t i = 0; i < voxels; ++i) {
    unsigned a = in[4 * i + 3];
    for (int c = 0; c < 3; ++c)
      out[4 * i + c] = std::uint8_t((in[4 * i + c] * a + 127) / 255);
    out[4 * i + 3] = std::uint8_t(a);
  }
}

VolumeSampler::VolumeSampler(const VolumeData& data) : data_(data) {
  if (!data.rgba.empty()) {
    premultiplied_.resize(data.rgba.size());
    premultiply_rgba8(data.rgba.data(), premultiplied_.data(), std::int64_t(data.rgba.size() / 4));
  }
}

Vec3 VolumeSampler::voxel_coords(Vec3 p) const {
  return div(p - data_.geometry.origin_mm, data_.geometry.spacing_mm);
}

namespace {

// Trilinear weights for one axis, clamped to the outer voxel centres (GL_CLAMP_TO_EDGE).
struct Axis {
  std::int64_t i0, i1;
  double f;
};
Axis axis(double v, std::int64_t n) {
  double c = std::clamp(v, 0.0, double(n - 1));
  if (!std::isfinite(c)) c = 0;
  std::int64_t i0 = std::min(std::int64_t(std::floor(c)), n - 1);
  return {i0, std::min(i0 + 1, n - 1), c - double(i0)};
}

template <class Fetch>
void trilinear(const LevelGeometry& g, Vec3 v, int components, Fetch fetch, double* out) {
  Axis ax = axis(v.x, g.dims[0]), ay = axis(v.y, g.dims[1]), az = axis(v.z, g.dims[2]);
  for (int c = 0; c < components; ++c)
    out[c] = 0;
  for (int k = 0; k < 8; ++k) {
    double w =
        ((k & 1) ? ax.f : 1 - ax.f) * ((k & 2) ? ay.f : 1 - ay.f) * ((k & 4) ? az.f : 1 - az.f);
    if (w == 0) continue;
    std::int64_t idx =
        ((k & 1) ? ax.i1 : ax.i0) +
        g.dims[0] * (((k & 2) ? ay.i1 : ay.i0) + g.dims[1] * ((k & 4) ? az.i1 : az.i0));
    for (int c = 0; c < components; ++c)
      out[c] += w * fetch(idx, c);
  }
}

}  // namespace

Rgba VolumeSampler::colour(Vec3 p) const {
  if (premultiplied_.empty()) return {};
  double out[4];
  const std::uint8_t* d = premultiplied_.data();
  trilinear(
      data_.geometry, voxel_coords(p), 4,
      [d](std::int64_t i, int c) { return double(d[4 * i + c]); }, out);
  return {float(out[0] / 255.0), float(out[1] / 255.0), float(out[2] / 255.0),
          float(out[3] / 255.0)};
}

double VolumeSampler::hu(Vec3 p) const {
  if (data_.ct.empty()) return 0.0;
  double out;
  const std::int16_t* d = data_.ct.data();
  // The GL texture is R16_SNORM: −32768 reads as −32767 (transfer.h).
  trilinear(
      data_.geometry, voxel_coords(p), 1,
      [d](std::int64_t i, int) { return double(std::max<std::int16_t>(d[i], -32767)); }, &out);
  return out;
}

Vec3 VolumeSampler::hu_gradient(Vec3 p) const {
  const Vec3 s = data_.geometry.spacing_mm;
  Vec3 g;
  for (int a = 0; a < 3; ++a) {
    Vec3 e{0, 0, 0};
    e[a] = s[a];
    g[a] = (hu(p + e) - hu(p - e)) / (2.0 * s[a]);
  }
  return g;
}

std::uint16_t VolumeSampler::label(Vec3 p) const {
  if (data_.labels.empty()) return 0;
  Vec3 v = voxel_coords(p);
  std::int64_t idx[3];
  for (int a = 0; a < 3; ++a) {
    double f = std::floor(v[a] + 0.5);
    if (!std::isfinite(f)) f = 0;
    idx[a] = std::clamp<std::int64_t>(std::int64_t(std::clamp(f, -1.0, 9e18)), 0,
                                      data_.geometry.dims[a] - 1);
  }
  return data_.labels[std::size_t(data_.index(idx[0], idx[1], idx[2]))];
}

double label_intensity(const VolumeSampler& sampler, const RenderParams& params, Vec3 p) {
  if (sampler.data().has(Channel::kCt))
    return window01(sampler.hu(p), params.window_center_hu, params.window_width_hu);
  Rgba c = sampler.colour(p);
  float inv = 1.0f / std::max(c.a, 1e-6f);
  return 0.299 * std::min(c.r * inv, 1.0f) + 0.587 * std::min(c.g * inv, 1.0f) +
         0.114 * std::min(c.b * inv, 1.0f);
}

Rgba classify(const VolumeSampler& sampler, const RenderParams& params, Vec3 p) {
  switch (params.mode) {
    case Mode::kColour: {
      Rgba c = sampler.colour(p);
      float inv = 1.0f / std::max(c.a, 1e-6f);
      Rgba out{std::min(c.r * inv, 1.0f), std::min(c.g * inv, 1.0f), std::min(c.b * inv, 1.0f), 0};
      double a = params.opacity_source == OpacitySource::kCt
                     ? window01(sampler.hu(p), params.window_center_hu, params.window_width_hu)
                     : double(c.a);
      out.a = float(params.opacity * a);
      return out;
    }
    case Mode::kCt: {
      double t = window01(sampler.hu(p), params.window_center_hu, params.window_width_hu);
      Rgba c = sample_ramp(params.ramp, t);
      c.a = float(params.opacity * t * c.a);
      return c;
    }
    case Mode::kLabels: {
      std::uint16_t id = sampler.label(p);
      if (id == 0 || params.label_colours.size() <= id) return {};
      Rgba c = params.label_colours[id];
      double f = (params.highlight_label >= 0 && int(id) != params.highlight_label)
                     ? params.dim_factor
                     : 1.0;
      c.a = float(c.a * params.opacity * f);
      if (params.label_shading != LabelShading::kFlat)
        c = shade_label(c, params.label_shading, label_intensity(sampler, params, p));
      return c;
    }
    case Mode::kTf2d: {
      Rgba c = params.tf2d.sample(sampler.hu(p), length(sampler.hu_gradient(p)));
      c.a = float(params.opacity * c.a);
      return c;
    }
    default:
      return {};
  }
}

double reference_length(const LevelGeometry& g) {
  double s = std::min({g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z});
  return s > 0 && std::isfinite(s) ? s : 1.0;
}

double slice_spacing(const Camera& camera, const LevelGeometry& g, double slices_per_voxel) {
  double s = std::isfinite(slices_per_voxel) ? std::clamp(slices_per_voxel, 1.0 / 64, 1024.0) : 2.0;
  return voxel_length_along(camera.forward, g.spacing_mm) / s;
}

double refine_iso(const VolumeSampler& sampler, const Ray& ray, double iso, double ta, double fa,
                  double tb, double fb) {
  for (int i = 0; i < kIsoBisectionSteps; ++i) {
    double tm = 0.5 * (ta + tb);
    double fm = sampler.hu(ray.origin + ray.direction * tm);
    if (fm >= iso) {
      tb = tm;
      fb = fm;
    } else {
      ta = tm;
      fa = fm;
    }
  }
  return fb > fa ? ta + (tb - ta) * (iso - fa) / (fb - fa) : tb;
}

namespace {

// Ray–box slab test: [t0, t1] of the ray inside the box, or false.
bool intersect(const Box3& box, const Ray& ray, double& t0, double& t1) {
  t0 = -std::numeric_limits<double>::infinity();
  t1 = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) {
    double o = ray.origin[a], d = ray.direction[a];
    if (std::fabs(d) < 1e-300) {
      if (o < box.lo[a] || o > box.hi[a]) return false;
      continue;
    }
    double ta = (box.lo[a] - o) / d, tb = (box.hi[a] - o) / d;
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
  }
  return t1 > t0;
}

Rgba resolve(Rgba acc, const Rgba& bg) {
  return {acc.r + (1 - acc.a) * bg.r, acc.g + (1 - acc.a) * bg.g, acc.b + (1 - acc.a) * bg.b,
          acc.a};
}

Rgba render_pixel(const VolumeSampler& sampler, const Camera& cam, const RenderParams& params,
                  double step, double delta0, const Box3& box, const Ray& ray) {
  const Rgba& bg = params.background;
  double t0, t1;
  if (!intersect(box, ray, t0, t1)) return resolve({}, bg);
  double cos_f = dot(ray.direction, cam.forward);
  if (!(cos_f > 1e-9)) return resolve({}, bg);
  double t_near = cam.orthographic ? cam.near_mm : cam.near_mm / cos_f;
  t0 = std::max(t0, t_near);
  if (!(t1 > t0)) return resolve({}, bg);
  auto clipped = [&](Vec3 p) { return params.clip && dot(params.clip_normal, p) > params.clip_d; };

  if (params.mode == Mode::kMpr) {
    Vec3 m = params.mpr_target + cam.forward * params.mpr_offset_mm;
    double t = dot(m - ray.origin, cam.forward) / cos_f;
    if (!(t >= t0 && t <= t1)) return resolve({}, bg);
    Vec3 p = ray.origin + ray.direction * t;
    if (clipped(p)) return resolve({}, bg);
    if (sampler.data().has(Channel::kRgba)) return resolve(sampler.colour(p), bg);
    Rgba c = sample_ramp(params.ramp,
                         window01(sampler.hu(p), params.window_center_hu, params.window_width_hu));
    c.a = 1;
    return c;
  }

  std::int64_t n = std::int64_t(std::ceil((t1 - t0) / step));
  n = std::clamp<std::int64_t>(n, 1, 10000000);
  if (params.mode == Mode::kMip || params.mode == Mode::kAverage) {
    double best = -std::numeric_limits<double>::infinity(), sum = 0, weight = 0;
    for (std::int64_t i = 0; i < n; ++i) {
      double a = t0 + double(i) * step, b = std::min(a + step, t1);
      Vec3 p = ray.origin + ray.direction * (0.5 * (a + b));
      if (clipped(p)) continue;
      double h = sampler.hu(p);
      best = std::max(best, h);
      sum += h * (b - a);
      weight += b - a;
    }
    if (!(weight > 0)) return resolve({}, bg);
    double v = params.mode == Mode::kMip ? best : sum / weight;
    Rgba c = sample_ramp(params.ramp, window01(v, params.window_center_hu, params.window_width_hu));
    c.a = 1;
    return c;
  }
  if (params.mode == Mode::kIso) {
    double t_prev = t0;
    double f_prev = sampler.hu(ray.origin + ray.direction * t0);
    bool prev_clipped = clipped(ray.origin + ray.direction * t0);
    for (std::int64_t i = 0; i <= n; ++i) {
      double t = i == 0 ? t0 : std::min(t0 + (double(i) - 0.5) * step, t1);
      Vec3 p = ray.origin + ray.direction * t;
      if (clipped(p)) {
        prev_clipped = true;
        continue;
      }
      double f = sampler.hu(p);
      if (f >= params.iso_hu) {
        double th = t;
        if (!prev_clipped && f_prev < params.iso_hu)
          th = refine_iso(sampler, ray, params.iso_hu, t_prev, f_prev, t, f);
        Vec3 hit = ray.origin + ray.direction * th;
        return shade_iso(params.iso_colour, sampler.hu_gradient(hit), ray.direction);
      }
      t_prev = t;
      f_prev = f;
      prev_clipped = false;
    }
    return resolve({}, bg);
  }
  // Compositing modes: front to back, early termination at 1 − 1e-5 (far below 8-bit output).
  Rgba acc;
  for (std::int64_t i = 0; i < n && acc.a < 0.99999f; ++i) {
    double a = t0 + double(i) * step, b = std::min(a + step, t1);
    Vec3 p = ray.origin + ray.direction * (0.5 * (a + b));
    if (clipped(p)) continue;
    Rgba s = classify(sampler, params, p);
    float alpha = float(opacity_correct(s.a, (b - a) / delta0));
    composite_under(acc, {s.r * alpha, s.g * alpha, s.b * alpha, alpha});
  }
  return resolve(acc, bg);
}

}  // namespace

ImageF render_reference(const VolumeData& data, const Camera& camera, const RenderParams& params,
                        const ReferenceOptions& options) {
  ImageF image(camera.width, camera.height);
  VolumeSampler sampler(data);
  Box3 box = data.geometry.box();
  double steps = options.steps_per_voxel > 0 ? options.steps_per_voxel : 16.0;
  double step = voxel_length_along(camera.forward, data.geometry.spacing_mm) / steps;
  double delta0 =
      params.reference_length_mm > 0 ? params.reference_length_mm : reference_length(data.geometry);
  parallel_for(camera.height, resolve_threads(options.threads), [&](std::int64_t y) {
    for (int x = 0; x < camera.width; ++x) {
      Ray ray = camera.ray(x + 0.5, double(y) + 0.5);
      Rgba c = render_pixel(sampler, camera, params, step, delta0, box, ray);
      float* px = image.at(x, int(y));
      px[0] = c.r;
      px[1] = c.g;
      px[2] = c.b;
      px[3] = c.a;
    }
  });
  return image;
}

}  // namespace vispack::render

// A small synthetic volume for the renderer tests: a soft ellipsoidal "body" (rgba coverage
// and smooth colours, blue gel with alpha 0 outside), CT with soft tissue and a "bone" sphere,
// labels 1 (left half of the body) and 3 (right half) side by side. Smooth edges (about two
// voxels wide) keep the renderers' sampling error small; labels stay sharp (nearest).
#pragma once

#include <algorithm>
#include <cmath>
#include <memory>

#include "vispack/render/volume.h"

namespace vispack::render::synthetic {

inline double smooth01(double x) {  // 0 below -1, 1 above +1, smooth in between
  double t = std::clamp(0.5 * (x + 1.0), 0.0, 1.0);
  return t * t * (3 - 2 * t);
}

inline std::shared_ptr<VolumeData> make_synthetic(int nx = 40, int ny = 32, int nz = 24,
                                                  Vec3 spacing = {1.0, 1.0, 1.5}) {
  auto v = std::make_shared<VolumeData>();
  v->geometry.dims = {nx, ny, nz};
  v->geometry.spacing_mm = spacing;
  v->geometry.origin_mm = {0, 0, 0};
  std::size_t n = std::size_t(nx) * ny * nz;
  v->rgba.resize(4 * n);
  v->ct.resize(n);
  v->labels.resize(n);
  v->label_table = {
      {1, "left", {220, 40, 40}}, {2, "never", {40, 220, 40}}, {3, "right", {40, 40, 220}}};
  Vec3 c{(nx - 1) / 2.0, (ny - 1) / 2.0, (nz - 1) / 2.0};
  for (int z = 0; z < nz; ++z)
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x) {
        std::size_t i = std::size_t(x + nx * (y + ny * z));
        // Ellipsoid radius in voxels: 0.4 of each dim; distance in voxel units.
        double ex = (x - c.x) / (0.4 * nx), ey = (y - c.y) / (0.4 * ny),
               ez = (z - c.z) / (0.4 * nz);
        double r = std::sqrt(ex * ex + ey * ey + ez * ez);
        double inside = smooth01((1.0 - r) * 0.4 * std::min({nx, ny, nz}) / 1.5);
        double bx = x - (c.x + 0.15 * nx), by = y - c.y, bz = (z - c.z) * spacing.z / spacing.x;
        double bone = smooth01((0.18 * ny - std::sqrt(bx * bx + by * by + bz * bz)) / 1.5);
        std::uint8_t a = std::uint8_t(std::lround(255 * inside));
        if (a == 0) {  // gel: blue, transparent (a halo would show it at the body's edge)
          v->rgba[4 * i + 0] = 30;
          v->rgba[4 * i + 1] = 60;
          v->rgba[4 * i + 2] = 200;
        } else {
          v->rgba[4 * i + 0] = std::uint8_t(150 + 90 * double(x) / nx);
          v->rgba[4 * i + 1] = std::uint8_t(90 + 100 * double(y) / ny);
          v->rgba[4 * i + 2] = std::uint8_t(60 + 60 * double(z) / nz);
        }
        v->rgba[4 * i + 3] = a;
        v->ct[i] = std::int16_t(std::lround(-1000 + 1040 * inside + 660 * bone * inside));
        v->labels[i] = inside > 0.5 ? (x < nx / 2 ? 1 : 3) : 0;
      }
  return v;
}

}  // namespace vispack::render::synthetic

#include "vispack/render/slicing.h"

#include <algorithm>
#include <cmath>

namespace vispack::render {

Box3 volume_box(const std::int64_t dims[3], Vec3 spacing_mm, Vec3 origin_mm) {
  Vec3 n{double(dims[0]), double(dims[1]), double(dims[2])};
  Box3 box;
  box.lo = origin_mm - spacing_mm * 0.5;
  box.hi = origin_mm + mul(n - Vec3{0.5, 0.5, 0.5}, spacing_mm);
  return box;
}

namespace {

struct P2 {
  double u, v;
  int index;  // into the 3-D point list
};

double cross2(const P2& o, const P2& a, const P2& b) {
  return (a.u - o.u) * (b.v - o.v) - (a.v - o.v) * (b.u - o.u);
}

}  // namespace

std::vector<Vec3> slice_polygon(const Box3& box, Vec3 normal, double d) {
  std::vector<Vec3> out;
  if (!box.valid() || !is_finite(normal) || !std::isfinite(d)) return out;
  double len = length(normal);
  if (!(len > 0) || !std::isfinite(len)) return out;
  Vec3 n = normal / len;
  d /= len;

  // Tolerances relative to the size of the problem (box extent, its distance from the origin
  // and |d|), so the same code works in micrometres and in metres.
  double scale = std::max({length(box.size()), length(box.lo), length(box.hi), std::fabs(d)});
  if (!(scale > 0)) scale = 1.0;
  const double on_plane = 1e-12 * scale;  // a vertex this close is on the plane
  const double merge = 1e-9 * scale;      // points this close are one point

  double s[8];
  for (int i = 0; i < 8; ++i) {
    s[i] = dot(n, box.corner(i)) - d;
    if (std::fabs(s[i]) <= on_plane) s[i] = 0.0;
  }
  std::vector<Vec3> pts;
  pts.reserve(12);
  for (int i = 0; i < 8; ++i)
    if (s[i] == 0.0) pts.push_back(box.corner(i));
  // The 12 edges: corner pairs differing in one bit.
  for (int i = 0; i < 8; ++i)
    for (int bit = 1; bit < 8; bit <<= 1) {
      int j = i | bit;
      if (j == i) continue;
      if ((s[i] < 0 && s[j] > 0) || (s[i] > 0 && s[j] < 0)) {
        double t = std::clamp(s[i] / (s[i] - s[j]), 0.0, 1.0);  // |s_i - s_j| > 2·on_plane
        Vec3 a = box.corner(i), b = box.corner(j);
        pts.push_back(a + (b - a) * t);
      }
    }
  if (pts.size() < 3) return out;

  // In-plane basis with u × v = −n, so counter-clockwise in (u, v) is counter-clockwise for a
  // viewer looking along n.
  Vec3 axis = std::fabs(n.x) < 0.57 ? Vec3{1, 0, 0}
                                    : (std::fabs(n.y) < 0.57 ? Vec3{0, 1, 0} : Vec3{0, 0, 1});
  Vec3 u = normalize_or(cross(n, axis), Vec3{1, 0, 0});
  Vec3 v = cross(u, n);
  std::vector<P2> p2;
  p2.reserve(pts.size());
  for (std::size_t i = 0; i < pts.size(); ++i)
    p2.push_back({dot(pts[i], u), dot(pts[i], v), int(i)});
  std::sort(p2.begin(), p2.end(),
            [](const P2& a, const P2& b) { return a.u < b.u || (a.u == b.u && a.v < b.v); });
  // Merge near-duplicates (plane through a corner gives the corner up to three times).
  std::vector<P2> uniq;
  for (const P2& p : p2) {
    bool dup = false;
    for (const P2& q : uniq)
      if (std::fabs(p.u - q.u) <= merge && std::fabs(p.v - q.v) <= merge) dup = true;
    if (!dup) uniq.push_back(p);
  }
  if (uniq.size() < 3) return out;
  // Andrew's monotone chain; cross <= area tolerance drops collinear points.
  const double area_eps = merge * length(box.size());  // areas scale with the box, not |lo|
  std::vector<P2> hull(2 * uniq.size());
  std::size_t k = 0;
  for (std::size_t i = 0; i < uniq.size(); ++i) {
    while (k >= 2 && cross2(hull[k - 2], hull[k - 1], uniq[i]) <= area_eps)
      --k;
    hull[k++] = uniq[i];
  }
  for (std::size_t i = uniq.size() - 1, t = k + 1; i-- > 0;) {
    while (k >= t && cross2(hull[k - 2], hull[k - 1], uniq[i]) <= area_eps)
      --k;
    hull[k++] = uniq[i];
  }
  hull.resize(k > 0 ? k - 1 : 0);
  if (hull.size() < 3) return out;
  double area = 0;
  for (std::size_t i = 0; i < hull.size(); ++i) {
    const P2& a = hull[i];
    const P2& b = hull[(i + 1) % hull.size()];
    area += a.u * b.v - a.v * b.u;
  }
  if (!(area * 0.5 > area_eps)) return out;
  out.reserve(hull.size());
  for (const P2& p : hull)
    out.push_back(pts[p.index]);
  return out;
}

double voxel_length_along(Vec3 n, Vec3 spacing_mm) {
  double smin = std::min({spacing_mm.x, spacing_mm.y, spacing_mm.z});
  if (!(smin > 0) || !is_finite(spacing_mm)) return 1.0;
  Vec3 unit = normalize_or(n, Vec3{0, 0, 1});
  double l = length(div(unit, spacing_mm));
  return l > 0 && std::isfinite(l) ? 1.0 / l : smin;
}

SliceLattice slice_lattice(const Box3& box, Vec3 normal, double spacing, double min_d,
                           std::int64_t max_slices) {
  SliceLattice lat;
  lat.spacing = spacing;
  if (!box.valid() || !is_finite(normal) || !std::isfinite(spacing) || !(spacing > 0)) return lat;
  double len = length(normal);
  if (!(len > 0) || !std::isfinite(len)) return lat;
  lat.normal = normal / len;
  double dmin = 1e300, dmax = -1e300;
  for (int i = 0; i < 8; ++i) {
    double d = dot(lat.normal, box.corner(i));
    dmin = std::min(dmin, d);
    dmax = std::max(dmax, d);
  }
  if (std::isfinite(min_d)) dmin = std::max(dmin, min_d);
  // Planes strictly inside (dmin, dmax): a plane that only touches the box draws nothing.
  double first = std::floor(dmin / spacing) + 1.0;
  double last = std::ceil(dmax / spacing) - 1.0;
  const double limit = 4e18;
  if (!std::isfinite(first) || std::fabs(first) > limit || max_slices <= 0) return lat;
  // A far plane beyond the integer range only matters through the cap below.
  if (!(last <= limit)) last = first + double(max_slices) - 1.0;
  if (last < first) return lat;
  double count = last - first + 1.0;
  if (count > double(max_slices)) count = double(max_slices);
  lat.first_k = static_cast<std::int64_t>(first);
  lat.count = static_cast<std::int64_t>(count);
  return lat;
}

double box_dmin(const Box3& box, Vec3 normal) {
  double len = length(normal);
  if (!box.valid() || !is_finite(normal) || !(len > 0)) return std::nan("");
  Vec3 n = normal / len;
  double dmin = 1e300;
  for (int i = 0; i < 8; ++i)
    dmin = std::min(dmin, dot(n, box.corner(i)));
  return dmin;
}

SliceLattice slice_lattice_tile(const Box3& box, Vec3 normal, double spacing, double min_d,
                                double volume_dmin, std::int64_t max_slices) {
  SliceLattice lat;
  lat.spacing = spacing;
  if (!box.valid() || !is_finite(normal) || !std::isfinite(spacing) || !(spacing > 0)) return lat;
  double len = length(normal);
  if (!(len > 0) || !std::isfinite(len)) return lat;
  lat.normal = normal / len;
  double dmin = 1e300, dmax = -1e300;
  for (int i = 0; i < 8; ++i) {
    double d = dot(lat.normal, box.corner(i));
    dmin = std::min(dmin, d);
    dmax = std::max(dmax, d);
  }
  // The lowest plane: d >= dmin (> dmin at the volume's own lowest face, and > min_d, the near
  // plane, as slice_lattice).
  double first = std::ceil(dmin / spacing);
  if (dmin <= volume_dmin && first * spacing <= dmin) first += 1.0;
  if (std::isfinite(min_d) && min_d >= dmin)
    first = std::max(first, std::floor(min_d / spacing) + 1.0);
  double last = std::ceil(dmax / spacing) - 1.0;  // d < dmax
  const double limit = 4e18;
  if (!std::isfinite(first) || std::fabs(first) > limit || max_slices <= 0) return lat;
  if (!(last <= limit)) last = first + double(max_slices) - 1.0;
  if (last < first) return lat;
  double count = last - first + 1.0;
  if (count > double(max_slices)) count = double(max_slices);
  lat.first_k = static_cast<std::int64_t>(first);
  lat.count = static_cast<std::int64_t>(count);
  return lat;
}

std::vector<Vec3> slice_triangles(const Box3& box, const SliceLattice& lattice,
                                  bool back_to_front) {
  std::vector<Vec3> tris;
  for (std::int64_t i = 0; i < lattice.count; ++i) {
    std::int64_t idx = back_to_front ? lattice.count - 1 - i : i;
    std::vector<Vec3> poly = slice_polygon(box, lattice.normal, lattice.d(idx));
    for (std::size_t j = 1; j + 1 < poly.size(); ++j) {
      tris.push_back(poly[0]);
      tris.push_back(poly[j]);
      tris.push_back(poly[j + 1]);
    }
  }
  return tris;
}

}  // namespace vispack::render

// Slicing geometry: every hard case of docs/GOALS.md §4.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <random>

#include "vispack/render/camera.h"
#include "vispack/render/slicing.h"

using namespace vispack::render;

namespace {

const Box3 kUnit{{0, 0, 0}, {1, 1, 1}};

// Signed area of the polygon measured along unit n (positive: counter-clockwise seen from +n).
double signed_area(const std::vector<Vec3>& p, Vec3 n) {
  Vec3 s{0, 0, 0};
  for (std::size_t i = 0; i < p.size(); ++i)
    s = s + cross(p[i], p[(i + 1) % p.size()]);
  return 0.5 * dot(s, n);
}

// Invariants every non-empty polygon must satisfy; tolerances are 1e-9 relative to the box
// (the slicer's own merge tolerance) .
void check_polygon(const std::vector<Vec3>& p, const Box3& box, Vec3 n, double d) {
  n = n / length(n);
  double scale = std::max(length(box.size()), 1.0);
  for (std::size_t i = 0; i < p.size(); ++i) {
    ASSERT_TRUE(is_finite(p[i]));
    EXPECT_NEAR(dot(n, p[i]), d, 1e-9 * scale);
    for (int a = 0; a < 3; ++a) {
      EXPECT_GE(p[i][a], box.lo[a] - 1e-9 * scale);
      EXPECT_LE(p[i][a], box.hi[a] + 1e-9 * scale);
    }
    for (std::size_t j = i + 1; j < p.size(); ++j)
      EXPECT_GT(length(p[i] - p[j]), 1e-9 * scale);
    // Convex and counter-clockwise seen looking along n: every turn is to the same side.
    Vec3 a = p[i], b = p[(i + 1) % p.size()], c = p[(i + 2) % p.size()];
    EXPECT_LT(dot(cross(b - a, c - b), n), 1e-12 * scale * scale);
  }
  if (!p.empty()) {
    EXPECT_LT(signed_area(p, n), 0.0);  // CCW for a viewer looking along +n
  }
}

double area(const std::vector<Vec3>& p, Vec3 n) {
  return std::fabs(signed_area(p, n / length(n)));
}

}  // namespace

TEST(Slicing, AxisAlignedViewsGiveTheFullRectangle) {
  Box3 box{{0, 0, 0}, {2, 3, 4}};
  const Vec3 normals[] = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}};
  const double areas[] = {12, 12, 8, 8, 6, 6};
  for (int i = 0; i < 6; ++i) {
    Vec3 n = normals[i];
    double d = dot(n, box.centre());
    auto p = slice_polygon(box, n, d);
    ASSERT_EQ(p.size(), 4u) << "normal " << i;
    check_polygon(p, box, n, d);
    EXPECT_NEAR(area(p, n), areas[i], 1e-12);
  }
}

TEST(Slicing, PlaneContainingAFaceGivesTheFace) {
  // Edges parallel to the plane and four corners exactly on it: four points, no duplicates.
  auto p = slice_polygon(kUnit, {0, 0, 1}, 1.0);
  ASSERT_EQ(p.size(), 4u);
  check_polygon(p, kUnit, {0, 0, 1}, 1.0);
  EXPECT_NEAR(area(p, {0, 0, 1}), 1.0, 1e-12);
}

TEST(Slicing, FaceAndBodyDiagonals) {
  Vec3 face{1, 1, 0};
  auto p = slice_polygon(kUnit, face, dot(face, kUnit.centre()));
  ASSERT_EQ(p.size(), 4u);
  EXPECT_NEAR(area(p, face), std::sqrt(2.0), 1e-12);
  Vec3 body{1, 1, 1};
  auto h = slice_polygon(kUnit, body, dot(body, kUnit.centre()));
  ASSERT_EQ(h.size(), 6u);  // the regular hexagon, side sqrt(2)/2: area 3*sqrt(3)/4
  EXPECT_NEAR(area(h, body), 3.0 * std::sqrt(3.0) / 4.0, 1e-12);
  check_polygon(h, kUnit, body, dot(body / length(body), kUnit.centre()));
}

TEST(Slicing, PlaneThroughCornersHasNoDuplicatePoints) {
  Vec3 n{1, 1, 1};
  // x + y + z = 1 passes through three corners; each is found from three edges.
  auto t = slice_polygon(kUnit, n, 1.0);
  ASSERT_EQ(t.size(), 3u);
  check_polygon(t, kUnit, n, 1.0 / std::sqrt(3.0));
  EXPECT_NEAR(area(t, n), std::sqrt(3.0) / 2.0, 1e-12);
  EXPECT_EQ(slice_polygon(kUnit, n, 2.0).size(), 3u);
  // Touching a single corner (x + y + z = 0 or 3) is no polygon.
  EXPECT_TRUE(slice_polygon(kUnit, n, 0.0).empty());
  EXPECT_TRUE(slice_polygon(kUnit, n, 3.0).empty());
}

TEST(Slicing, PlaneContainingEdges) {
  // x + y = 1 contains the edges (1,0,z) and (0,1,z): four corners, each also an edge cut.
  auto p = slice_polygon(kUnit, {1, 1, 0}, 1.0);
  ASSERT_EQ(p.size(), 4u);
  EXPECT_NEAR(area(p, {1, 1, 0}), std::sqrt(2.0), 1e-12);
  // x + y = 0 only touches the edge (0,0,z): a segment is no polygon.
  EXPECT_TRUE(slice_polygon(kUnit, {1, 1, 0}, 0.0).empty());
}

TEST(Slicing, NearParallelEdgesUseRelativeTolerances) {
  // Denominators of ~1e-7 (the edge is almost parallel to the plane).
  for (double eps : {1e-7, 1e-9, 1e-13, 0.0}) {
    Vec3 n{eps, 0, 1};
    double d = 0.5 * length(n);
    auto p = slice_polygon(kUnit, n, d);
    ASSERT_EQ(p.size(), 4u) << eps;
    check_polygon(p, kUnit, n, 0.5);
    EXPECT_NEAR(area(p, n), 1.0, 1e-6) << eps;
  }
  // Almost through a corner: still a clean triangle, finite points.
  Vec3 n{1, 1, 1};
  for (double eps : {1e-7, 1e-12, 1e-15}) {
    auto t = slice_polygon(kUnit, n, 1.0 + eps);
    ASSERT_GE(t.size(), 3u) << eps;
    ASSERT_LE(t.size(), 6u) << eps;
    check_polygon(t, kUnit, n, (1.0 + eps) / std::sqrt(3.0));
  }
  // Same in a box far from the origin in metres-sized units (tolerances are relative).
  Box3 far{{1e5, 2e5, -3e5}, {1e5 + 0.2, 2e5 + 0.3, -3e5 + 0.4}};
  Vec3 m{1e-8, 1, 0};
  auto q = slice_polygon(far, m, dot(m / length(m), far.centre()) * length(m));
  EXPECT_EQ(q.size(), 4u);
}

TEST(Slicing, CrossSectionsIntegrateToTheBoxVolume) {
  // Cavalieri: the integral of the section area over d is the volume. Random boxes and normals.
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int trial = 0; trial < 20; ++trial) {
    Box3 box{{u(rng), u(rng), u(rng)}, {}};
    box.hi =
        box.lo + Vec3{0.2 + std::fabs(u(rng)), 0.2 + std::fabs(u(rng)), 0.2 + std::fabs(u(rng))};
    Vec3 n = normalize_or({u(rng), u(rng), u(rng)}, {0, 0, 1});
    double dmin = 1e9, dmax = -1e9;
    for (int i = 0; i < 8; ++i) {
      dmin = std::min(dmin, dot(n, box.corner(i)));
      dmax = std::max(dmax, dot(n, box.corner(i)));
    }
    const int steps = 4000;
    double h = (dmax - dmin) / steps, vol = 0;
    for (int i = 0; i < steps; ++i) {
      double d = dmin + (i + 0.5) * h;
      auto p = slice_polygon(box, n, d);
      if (i % 97 == 0) check_polygon(p, box, n, d);
      vol += area(p, n) * h;
    }
    Vec3 s = box.size();
    // Midpoint rule on a piecewise-quadratic area: relative error far below 1e-5.
    EXPECT_NEAR(vol, s.x * s.y * s.z, 1e-5 * s.x * s.y * s.z) << "trial " << trial;
  }
}

TEST(Slicing, InvalidInputNeverHangs) {
  const double nan = std::nan("");
  const double inf = INFINITY;
  EXPECT_TRUE(slice_polygon({{nan, 0, 0}, {1, 1, 1}}, {0, 0, 1}, 0.5).empty());
  EXPECT_TRUE(slice_polygon({{0, 0, 0}, {1, inf, 1}}, {0, 0, 1}, 0.5).empty());
  EXPECT_TRUE(slice_polygon(kUnit, {nan, 0, 1}, 0.5).empty());
  EXPECT_TRUE(slice_polygon(kUnit, {0, 0, 0}, 0.5).empty());
  EXPECT_TRUE(slice_polygon(kUnit, {0, 0, 1}, nan).empty());
  EXPECT_TRUE(slice_polygon({{1, 1, 1}, {0, 0, 0}}, {0, 0, 1}, 0.5).empty());  // inverted box
  EXPECT_EQ(slice_lattice({{nan, 0, 0}, {1, 1, 1}}, {0, 0, 1}, 0.1, -inf).count, 0);
  EXPECT_EQ(slice_lattice(kUnit, {0, 0, 1}, nan, -inf).count, 0);
  EXPECT_EQ(slice_lattice(kUnit, {0, 0, 1}, 0.0, -inf).count, 0);
  EXPECT_EQ(slice_lattice(kUnit, {0, 0, 1}, -0.1, -inf).count, 0);
  EXPECT_EQ(slice_lattice(kUnit, {0, 0, 1}, inf, -inf).count, 0);
  EXPECT_EQ(slice_lattice(kUnit, {nan, nan, nan}, 0.1, -inf).count, 0);
  // A huge box with a tiny spacing is capped, and returns at once.
  auto t0 = std::chrono::steady_clock::now();
  SliceLattice big = slice_lattice({{-1e300, -1, -1}, {1e300, 1, 1}}, {1, 0, 0}, 1e-300, -inf, 500);
  EXPECT_LE(big.count, 500);
  EXPECT_EQ(slice_lattice(kUnit, {0, 0, 1}, 1e-320, -inf, 1000).count, 1000);
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), 1.0);
}

TEST(Slicing, OneVoxelThickVolume) {
  const std::int64_t dims[3] = {10, 8, 1};
  Box3 box = volume_box(dims, {1, 1, 1}, {0, 0, 0});
  EXPECT_DOUBLE_EQ(box.size().z, 1.0);
  for (Vec3 n : {Vec3{0, 0, 1}, Vec3{1, 0, 0}, Vec3{0.3, 0.2, 0.9}}) {
    n = n / length(n);
    SliceLattice lat = slice_lattice(box, n, voxel_length_along(n, {1, 1, 1}) / 2, -INFINITY);
    ASSERT_GE(lat.count, 1);
    for (std::int64_t i = 0; i < lat.count; ++i) {
      auto p = slice_polygon(box, n, lat.d(i));
      EXPECT_GE(p.size(), 3u);
      check_polygon(p, box, n, lat.d(i));
    }
  }
  // A zero-thickness box viewed edge-on has no slices; viewed face-on one face.
  Box3 flat{{0, 0, 0}, {1, 1, 0}};
  EXPECT_EQ(slice_polygon(flat, {0, 0, 1}, 0.0).size(), 4u);
  EXPECT_TRUE(slice_polygon(flat, {1, 0, 0}, 0.5).empty());
}

TEST(Slicing, LatticeIsFixedInWorldSpace) {
  // Translating the camera (same direction) leaves every slice plane where it was.
  const std::int64_t dims[3] = {40, 32, 24};
  Box3 box = volume_box(dims, {1, 1, 1.5}, {0, 0, 0});
  OrbitParams o;
  o.target = box.centre();
  o.azimuth_deg = 33;
  o.elevation_deg = 21;
  Camera a = orbit_camera(o, box, 64, 64);
  o.pan_mm = {10.37, -4.71, 2.23};
  Camera b = orbit_camera(o, box, 64, 64);
  ASSERT_NEAR(length(a.forward - b.forward), 0.0, 1e-15);
  double delta = voxel_length_along(a.forward, {1, 1, 1.5}) / 2;
  SliceLattice la = slice_lattice(box, a.forward, delta, dot(a.forward, a.eye) + a.near_mm);
  SliceLattice lb = slice_lattice(box, b.forward, delta, dot(b.forward, b.eye) + b.near_mm);
  EXPECT_EQ(la.first_k, lb.first_k);
  EXPECT_EQ(la.count, lb.count);
  EXPECT_GT(la.count, 40);
  auto ta = slice_triangles(box, la), tb = slice_triangles(box, lb);
  ASSERT_EQ(ta.size(), tb.size());
  for (std::size_t i = 0; i < ta.size(); ++i)
    EXPECT_EQ(length(ta[i] - tb[i]), 0.0);
  // Planes are back to front: the first triangle is the farthest from the eye.
  EXPECT_GT(dot(a.forward, ta.front()), dot(a.forward, ta.back()));
}

TEST(Slicing, CameraInsideTheVolumeDropsPlanesBehindIt) {
  const std::int64_t dims[3] = {20, 20, 20};
  Box3 box = volume_box(dims, {1, 1, 1}, {0, 0, 0});
  OrbitParams o;
  o.target = box.centre();
  o.distance_mm = 3.0;  // eye 3 mm from the centre, well inside
  Camera cam = orbit_camera(o, box, 32, 32);
  EXPECT_GT(cam.near_mm, 0.0);
  double min_d = dot(cam.forward, cam.eye) + cam.near_mm;
  SliceLattice all = slice_lattice(box, cam.forward, 0.5, -INFINITY);
  SliceLattice front = slice_lattice(box, cam.forward, 0.5, min_d);
  EXPECT_EQ(all.count, 39);  // planes strictly inside a 20 mm box at 0.5 mm
  // The eye (y = 12.5) looks along -y; the face it looks at is at y = -0.5, 13 mm away:
  // planes at y = 12.0, 11.5, ..., 0.0 (d = -y).
  EXPECT_EQ(front.count, 25);
  for (std::int64_t i = 0; i < front.count; ++i)
    EXPECT_GT(front.d(i), min_d);
}

TEST(Slicing, AnisotropicVoxelLength) {
  Vec3 sp{0.33, 0.33, 1.0};
  EXPECT_NEAR(voxel_length_along({0, 0, 1}, sp), 1.0, 1e-15);
  EXPECT_NEAR(voxel_length_along({1, 0, 0}, sp), 0.33, 1e-15);
  // Along (1,0,1)/sqrt2: 1/sqrt((0.5/0.33^2) + 0.5).
  double expect = 1.0 / std::sqrt(0.5 / (0.33 * 0.33) + 0.5);
  EXPECT_NEAR(voxel_length_along({1, 0, 1}, sp), expect, 1e-15);
}

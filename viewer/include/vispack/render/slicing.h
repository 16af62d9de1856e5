// View-aligned slicing geometry: the proxy polygons a slice renderer draws (docs/GOALS.md §4).
//
// A slice is the intersection of the volume's box with a plane n·x = d (n a unit vector,
// x and d in world mm). Planes sit on a lattice fixed in world space: d = k·Δ for integer k,
// so the set of planes depends only on n and Δ, never on where the camera is (slices do not
// swim under translation).
//
// Robustness (every degenerate case of docs/GOALS.md §4): vertices are classified against the
// plane with a tolerance relative to the box size and |d|; a vertex within it counts as on the
// plane (no division), an edge is cut only when its endpoints are strictly on opposite sides
// (the denominator is then at least twice the tolerance, and the parameter is clamped to
// [0, 1]). The points are merged within the tolerance and ordered by a 2-D convex hull in the
// plane, which removes duplicates (plane through a corner or containing an edge) and collinear
// points. A result with fewer than 3 points, or of zero area, is empty. Non-finite input
// (NaN box, NaN normal) gives an empty polygon; nothing here loops on a floating-point count.
#pragma once

#include <cstdint>
#include <vector>

#include "vispack/render/math.h"

namespace vispack::render {

// Axis-aligned box in world mm. Valid when every bound is finite and lo <= hi on each axis
// (a zero-thickness box is valid: its slices along that axis are the whole face).
struct Box3 {
  Vec3 lo{0, 0, 0};
  Vec3 hi{0, 0, 0};
  bool valid() const {
    return is_finite(lo) && is_finite(hi) && lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z;
  }
  Vec3 centre() const { return (lo + hi) * 0.5; }
  Vec3 size() const { return hi - lo; }
  Vec3 corner(int i) const {
    return {(i & 1) ? hi.x : lo.x, (i & 2) ? hi.y : lo.y, (i & 4) ? hi.z : lo.z};
  }
};

// Box of a voxel grid: voxel (i, j, k) has its centre at origin + (i, j, k)·spacing and covers
// half a spacing on each side, so the box is [origin − spacing/2, origin + (dims − 1/2)·spacing].
Box3 volume_box(const std::int64_t dims[3], Vec3 spacing_mm, Vec3 origin_mm);

// Convex polygon of box ∩ {x : normal·x = d}, counter-clockwise seen from the side `normal`
// points away from (i.e. looking along `normal`, as the camera does), as world points.
// `normal` need not be unit length (it is normalised; d is then scaled accordingly).
// Empty when the plane misses the box, touches it in a point or segment, or input is invalid.
std::vector<Vec3> slice_polygon(const Box3& box, Vec3 normal, double d);

// Length of one voxel along unit direction n: the distance that advances one unit in voxel
// index space, 1 / |(n.x/sx, n.y/sy, n.z/sz)|. Equals the spacing for isotropic voxels.
double voxel_length_along(Vec3 n, Vec3 spacing_mm);

// The planes k·Δ (k integer) that cut the box, limited to d >= min_d (the near plane: planes
// behind the camera are dropped). `count` is capped at `max_slices` (the planes nearest to
// min_d... first_k upward are kept). Empty (count = 0) for invalid input: NaN/inf box or normal,
// Δ <= 0 or non-finite.
struct SliceLattice {
  Vec3 normal{0, 0, 1};      // unit
  double spacing = 1.0;      // Δ in mm
  std::int64_t first_k = 0;  // plane k has d = k * spacing
  std::int64_t count = 0;
  double d(std::int64_t i) const { return double(first_k + i) * spacing; }
};
SliceLattice slice_lattice(const Box3& box, Vec3 normal, double spacing, double min_d,
                           std::int64_t max_slices = 100000);

// The same lattice for one box of several that tile a volume (the brick-paged renderer): the
// planes with d in [dmin, dmax) of `box` (half-open: a plane through the box's lowest face or
// corner belongs to it, one through its highest does not), so that every plane crossing a tiled
// volume is drawn by exactly one box even when it contains a shared face (views along an axis).
// `volume_dmin` is the whole volume's dmin along `normal`: a plane exactly there only touches
// the volume and is dropped, as slice_lattice drops it.
SliceLattice slice_lattice_tile(const Box3& box, Vec3 normal, double spacing, double min_d,
                                double volume_dmin, std::int64_t max_slices = 100000);
// Smallest n·x over the corners of `box` (n normalised), NaN for invalid input.
double box_dmin(const Box3& box, Vec3 normal);

// Triangle list (3 world points per triangle, a fan over each polygon) of every slice of the
// lattice, ordered back to front (largest d first) when `back_to_front`, else front to back.
std::vector<Vec3> slice_triangles(const Box3& box, const SliceLattice& lattice,
                                  bool back_to_front = true);

}  // namespace vispack::render

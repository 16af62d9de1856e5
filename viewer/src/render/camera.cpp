#include "vispack/render/camera.h"

#include <algorithm>
#include <cmath>

#include "vispack/common/math_constants.h"
#include "vispack/render/slicing.h"

namespace vispack::render {
namespace {
double finite_or(double v, double fallback) {
  return std::isfinite(v) ? v : fallback;
}
}  // namespace

Ray Camera::ray(double px, double py) const {
  double aspect = double(width) / double(std::max(height, 1));
  double nx = px / double(std::max(width, 1)) * 2.0 - 1.0;
  double ny = 1.0 - py / double(std::max(height, 1)) * 2.0;
  if (orthographic) {
    Vec3 origin = eye + right * (nx * ortho_half_height * aspect) + up * (ny * ortho_half_height);
    return {origin, forward};
  }
  double t = std::tan(fov_y_deg * kPi / 360.0);
  Vec3 dir = forward + right * (nx * t * aspect) + up * (ny * t);
  return {eye, normalize_or(dir, forward)};
}

Mat4 Camera::view_matrix() const {
  Mat4 v = Mat4::identity();
  const Vec3 rows[3] = {right, up, -forward};
  for (int r = 0; r < 3; ++r) {
    v.m[0][r] = rows[r].x;
    v.m[1][r] = rows[r].y;
    v.m[2][r] = rows[r].z;
    v.m[3][r] = -dot(rows[r], eye);
  }
  return v;
}

Mat4 Camera::projection_matrix() const {
  Mat4 p;
  double aspect = double(width) / double(std::max(height, 1));
  double n = near_mm, f = far_mm;
  if (orthographic) {
    p.m[0][0] = 1.0 / (ortho_half_height * aspect);
    p.m[1][1] = 1.0 / ortho_half_height;
    p.m[2][2] = -2.0 / (f - n);
    p.m[3][2] = -(f + n) / (f - n);
    p.m[3][3] = 1.0;
  } else {
    double c = 1.0 / std::tan(fov_y_deg * kPi / 360.0);
    p.m[0][0] = c / aspect;
    p.m[1][1] = c;
    p.m[2][2] = (f + n) / (n - f);
    p.m[3][2] = 2.0 * f * n / (n - f);
    p.m[2][3] = -1.0;
  }
  return p;
}

double fit_distance(const Box3& box, double fov_y_deg) {
  if (!box.valid()) return 1.0;
  double radius = std::max(length(box.size()) * 0.5, 1e-9);
  double half = std::clamp(finite_or(fov_y_deg, 30.0), 1.0, 170.0) * kPi / 360.0;
  return radius / std::sin(half);
}

Camera orbit_camera(const OrbitParams& params, const Box3& box, int width, int height) {
  Camera cam;
  cam.width = std::max(width, 1);
  cam.height = std::max(height, 1);
  cam.orthographic = params.orthographic;
  cam.fov_y_deg = std::clamp(finite_or(params.fov_y_deg, 30.0), 1.0, 170.0);
  double zoom = finite_or(params.zoom, 1.0);
  if (!(zoom > 0)) zoom = 1.0;
  double az = finite_or(params.azimuth_deg, 0.0) * kPi / 180.0;
  double el = std::clamp(finite_or(params.elevation_deg, 0.0), -89.9, 89.9) * kPi / 180.0;
  Vec3 target = is_finite(params.target) ? params.target : Vec3{};
  Vec3 pan = is_finite(params.pan_mm) ? params.pan_mm : Vec3{};
  double fit = fit_distance(box, cam.fov_y_deg);
  double distance = finite_or(params.distance_mm, 0.0);
  if (!(distance > 0)) distance = fit / zoom;

  cam.forward = Vec3{std::sin(az) * std::cos(el), -std::cos(az) * std::cos(el), std::sin(el)};
  cam.eye = target - cam.forward * distance + pan;
  cam.right = normalize_or(cross(cam.forward, Vec3{0, 0, -1}), Vec3{1, 0, 0});
  cam.up = cross(cam.right, cam.forward);
  double radius = box.valid() ? std::max(length(box.size()) * 0.5, 1e-9) : 1.0;
  cam.ortho_half_height = radius / zoom;

  // Near/far enclose the box; an eye inside the box gets a small positive near plane.
  double diag = 2.0 * radius;
  double dmin = 1e300, dmax = -1e300;
  for (int i = 0; i < 8; ++i) {
    double d = dot((box.valid() ? box.corner(i) : target) - cam.eye, cam.forward);
    dmin = std::min(dmin, d);
    dmax = std::max(dmax, d);
  }
  cam.near_mm = std::max(dmin - 1e-3 * diag, 1e-3 * diag);
  cam.far_mm = std::max(dmax + 1e-3 * diag, cam.near_mm * 2.0);
  return cam;
}

}  // namespace vispack::render

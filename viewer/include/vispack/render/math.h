// Small vector and matrix types for the viewer's geometry (double precision on the CPU; the GL
// code converts to float when it uploads). No dependency beyond <cmath>.
//
// Mat4 is column-major (m[column][row]), the layout glUniformMatrix4fv expects with
// transpose = GL_FALSE; it multiplies column vectors: p' = M * p.
#pragma once

#include <array>
#include <cmath>

namespace vispack::render {

struct Vec3 {
  double x = 0, y = 0, z = 0;
  constexpr Vec3() = default;
  constexpr Vec3(double x_, double y_, double z_) : x(x_), y(y_), z(z_) {}
  double operator[](int i) const { return i == 0 ? x : (i == 1 ? y : z); }
  double& operator[](int i) { return i == 0 ? x : (i == 1 ? y : z); }
};

inline Vec3 operator+(Vec3 a, Vec3 b) {
  return {a.x + b.x, a.y + b.y, a.z + b.z};
}
inline Vec3 operator-(Vec3 a, Vec3 b) {
  return {a.x - b.x, a.y - b.y, a.z - b.z};
}
inline Vec3 operator-(Vec3 a) {
  return {-a.x, -a.y, -a.z};
}
inline Vec3 operator*(Vec3 a, double s) {
  return {a.x * s, a.y * s, a.z * s};
}
inline Vec3 operator*(double s, Vec3 a) {
  return a * s;
}
inline Vec3 operator/(Vec3 a, double s) {
  return {a.x / s, a.y / s, a.z / s};
}
// Component-wise product and quotient.
inline Vec3 mul(Vec3 a, Vec3 b) {
  return {a.x * b.x, a.y * b.y, a.z * b.z};
}
inline Vec3 div(Vec3 a, Vec3 b) {
  return {a.x / b.x, a.y / b.y, a.z / b.z};
}
inline double dot(Vec3 a, Vec3 b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
inline Vec3 cross(Vec3 a, Vec3 b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline double length(Vec3 a) {
  return std::sqrt(dot(a, a));
}
// Unit vector along `a`; returns `fallback` when |a| is zero or not finite (never NaN).
inline Vec3 normalize_or(Vec3 a, Vec3 fallback) {
  double len = length(a);
  if (!(len > 1e-300) || !std::isfinite(len)) return fallback;
  return a / len;
}
inline bool is_finite(Vec3 a) {
  return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z);
}
inline Vec3 min(Vec3 a, Vec3 b) {
  return {std::fmin(a.x, b.x), std::fmin(a.y, b.y), std::fmin(a.z, b.z)};
}
inline Vec3 max(Vec3 a, Vec3 b) {
  return {std::fmax(a.x, b.x), std::fmax(a.y, b.y), std::fmax(a.z, b.z)};
}

struct Vec4 {
  double x = 0, y = 0, z = 0, w = 0;
};

struct Mat4 {
  std::array<std::array<double, 4>, 4> m{};  // m[column][row]
  static Mat4 identity() {
    Mat4 r;
    for (int i = 0; i < 4; ++i)
      r.m[i][i] = 1;
    return r;
  }
  // Column-major floats for glUniformMatrix4fv(..., GL_FALSE, ...).
  std::array<float, 16> to_float() const {
    std::array<float, 16> out{};
    for (int c = 0; c < 4; ++c)
      for (int r = 0; r < 4; ++r)
        out[c * 4 + r] = static_cast<float>(m[c][r]);
    return out;
  }
};

inline Mat4 operator*(const Mat4& a, const Mat4& b) {
  Mat4 r;
  for (int c = 0; c < 4; ++c)
    for (int row = 0; row < 4; ++row) {
      double s = 0;
      for (int k = 0; k < 4; ++k)
        s += a.m[k][row] * b.m[c][k];
      r.m[c][row] = s;
    }
  return r;
}
inline Vec4 operator*(const Mat4& a, Vec4 v) {
  double in[4] = {v.x, v.y, v.z, v.w}, out[4] = {0, 0, 0, 0};
  for (int row = 0; row < 4; ++row)
    for (int k = 0; k < 4; ++k)
      out[row] += a.m[k][row] * in[k];
  return {out[0], out[1], out[2], out[3]};
}

}  // namespace vispack::render

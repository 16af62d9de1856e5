// Mathematical constants shared by every module (one definition of pi for the whole project).
#pragma once

namespace vispack {

inline constexpr double kPi = 3.14159265358979323846;

// Degrees <-> radians.
inline constexpr double radians(double degrees) {
  return degrees * kPi / 180.0;
}
inline constexpr double degrees(double radians) {
  return radians * 180.0 / kPi;
}

}  // namespace vispack

// Internal: the integer arithmetic the format's sources share (brick counts, level sizes,
// overflow-checked byte counts). Not installed. Pure functions; thread-safe.
#pragma once

#include <cstdint>
#include <limits>
#include <optional>

namespace vispack::format::detail {

// ceil(a / b) for a >= 0 and b > 0.
inline std::int64_t ceil_div(std::int64_t a, std::int64_t b) {
  return (a + b - 1) / b;
}

// a * b, or nullopt when it overflows uint64.
inline std::optional<std::uint64_t> mul(std::uint64_t a, std::uint64_t b) {
  if (a != 0 && b > std::numeric_limits<std::uint64_t>::max() / a) return std::nullopt;
  return a * b;
}

// a + b, or nullopt when it overflows uint64.
inline std::optional<std::uint64_t> add(std::uint64_t a, std::uint64_t b) {
  if (b > std::numeric_limits<std::uint64_t>::max() - a) return std::nullopt;
  return a + b;
}

}  // namespace vispack::format::detail

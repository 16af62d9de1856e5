#include "vispack/format/downsample.h"

namespace vispack::format {
namespace {

// floor((2 * sum + n) / (2 * n)) for any sign of sum: round half up, exact.
std::int64_t round_div(std::int64_t sum, std::int64_t n) {
  std::int64_t num = 2 * sum + n, den = 2 * n;
  std::int64_t q = num / den;
  if ((num % den != 0) && (num < 0)) --q;  // C++ truncates toward zero; we want floor
  return q;
}

}  // namespace

std::int16_t reduce_mean_i16(const std::int16_t* children, int count) {
  std::int64_t sum = 0;
  for (int i = 0; i < count; ++i)
    sum += children[i];
  return std::int16_t(round_div(sum, count));
}

std::array<std::uint8_t, 4> reduce_rgba_alpha_weighted(const std::uint8_t* children, int count) {
  std::int64_t sum_a = 0;
  std::int64_t sum_c[3] = {0, 0, 0};
  std::int64_t sum_ca[3] = {0, 0, 0};
  for (int i = 0; i < count; ++i) {
    const std::uint8_t* v = children + 4 * i;
    sum_a += v[3];
    for (int c = 0; c < 3; ++c) {
      sum_c[c] += v[c];
      sum_ca[c] += std::int64_t(v[c]) * v[3];
    }
  }
  std::array<std::uint8_t, 4> out{};
  for (int c = 0; c < 3; ++c) {
    out[c] = std::uint8_t(sum_a > 0 ? round_div(sum_ca[c], sum_a) : round_div(sum_c[c], count));
  }
  out[3] = std::uint8_t(round_div(sum_a, count));
  return out;
}

std::uint16_t reduce_majority(const std::uint16_t* children, int count) {
  // At most 8 children: count by pairwise comparison, no allocation.
  std::uint16_t best = children[0];
  int best_count = 0;
  for (int i = 0; i < count; ++i) {
    std::uint16_t id = children[i];
    int n = 0;
    for (int j = 0; j < count; ++j)
      n += children[j] == id;
    bool better = n > best_count || (n == best_count && id != 0 && (best == 0 || id < best));
    if (better) {
      best = id;
      best_count = n;
    }
  }
  return best;
}

}  // namespace vispack::format

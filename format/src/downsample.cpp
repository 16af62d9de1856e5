#include "vispack/format/downsample.h"

#include <algorithm>
#include <cstring>
#include <vector>

#include "int_math.h"
#include "vispack/common/parallel.h"
#include "vispack/common/zero_paged_buffer.h"

namespace vispack::format {
namespace {

// floor((2 * sum + n) / (2 * n)) for any sign of sum: round half up, exact.
std::int64_t round_div(std::int64_t sum, std::int64_t n) {
  std::int64_t num = 2 * sum + n, den = 2 * n;
  std::int64_t q = num / den;
  if ((num % den != 0) && (num < 0)) --q;  // C++ truncates toward zero; we want floor
  return q;
}

using detail::ceil_div;

// The tie-break of reduce_majority: does `id` seen `n` times beat `best` seen `best_n` times?
inline bool beats(std::uint16_t id, std::size_t n, std::uint16_t best, std::size_t best_n) {
  return n > best_n || (n == best_n && id != 0 && (best == 0 || id < best));
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

std::uint16_t reduce_majority(const std::uint16_t* ids, std::size_t count) {
  std::uint16_t best = ids[0];
  std::size_t best_n = 0;
  if (count <= 8) {
    // Count by pairwise comparison, no allocation (the pyramid's hot path).
    for (std::size_t i = 0; i < count; ++i) {
      const std::uint16_t id = ids[i];
      std::size_t n = 0;
      for (std::size_t j = 0; j < count; ++j)
        n += ids[j] == id;
      if (beats(id, n, best, best_n)) {
        best = id;
        best_n = n;
      }
    }
    return best;
  }
  std::vector<std::uint16_t> sorted(ids, ids + count);
  std::sort(sorted.begin(), sorted.end());
  for (std::size_t i = 0; i < sorted.size();) {
    std::size_t j = i;
    while (j < sorted.size() && sorted[j] == sorted[i])
      ++j;
    if (beats(sorted[i], j - i, best, best_n)) {
      best = sorted[i];
      best_n = j - i;
    }
    i = j;
  }
  return best;
}

namespace {

// Reduces the children of output voxel (x, y) in the general case (fewer than eight children
// at the volume's edges), gathering them in z, y, x order as the reduce_* functions expect.
void reduce_generic(ChannelType type, const std::uint8_t* src, int nzc, std::int64_t dx,
                    std::int64_t dy, std::int64_t x, std::int64_t y, std::uint8_t* out) {
  const std::size_t bytes = channel_type_bytes(type);
  const std::size_t plane = std::size_t(dx) * std::size_t(dy);
  std::uint8_t children[8 * 4];
  int n = 0;
  for (int z = 0; z < nzc; ++z) {
    for (std::int64_t yy = 2 * y; yy < std::min(dy, 2 * y + 2); ++yy) {
      for (std::int64_t xx = 2 * x; xx < std::min(dx, 2 * x + 2); ++xx) {
        std::memcpy(children + n * bytes, src + (z * plane + yy * dx + xx) * bytes, bytes);
        ++n;
      }
    }
  }
  switch (type) {
    case ChannelType::kRgba8: {
      auto v = reduce_rgba_alpha_weighted(children, n);
      std::memcpy(out, v.data(), 4);
      break;
    }
    case ChannelType::kInt16: {
      std::int16_t c[8];
      std::memcpy(c, children, 2 * n);
      std::int16_t v = reduce_mean_i16(c, n);
      std::memcpy(out, &v, 2);
      break;
    }
    case ChannelType::kUint8: {
      std::uint16_t c[8];
      for (int i = 0; i < n; ++i)
        c[i] = children[i];
      *out = std::uint8_t(reduce_majority(c, n));
      break;
    }
    case ChannelType::kUint16: {
      std::uint16_t c[8];
      std::memcpy(c, children, 2 * n);
      std::uint16_t v = reduce_majority(c, n);
      std::memcpy(out, &v, 2);
      break;
    }
  }
}

// Fast paths for an output voxel with all eight children present. Each gives exactly the
// result of the reduce_* function on the same children (integer arithmetic only):
//   mean of 8:      round_div(sum, 8) = floor((2 * sum + 8) / 16) = (sum + 4) >> 3 (floor shift);
//   alpha-weighted: when all eight alphas are equal (alpha > 0, or all 0), the weighted mean
//                   round_div(alpha * sum_c, 8 * alpha) equals round_div(sum_c, 8);
//   majority:       eight equal IDs give that ID.
// `r[k]` points at the first child of row k (k = 2 * z + y), x pairs adjacent.
inline void reduce8_rgba(const std::uint8_t* const r[4], std::uint8_t* out) {
  std::uint32_t sum_a = 0, a_min = 255, a_max = 0;
  for (int k = 0; k < 4; ++k) {
    for (int i = 0; i < 2; ++i) {
      std::uint32_t a = r[k][4 * i + 3];
      sum_a += a;
      a_min = std::min(a_min, a);
      a_max = std::max(a_max, a);
    }
  }
  if (a_min == a_max) {
    for (int c = 0; c < 3; ++c) {
      std::uint32_t s = 0;
      for (int k = 0; k < 4; ++k)
        s += std::uint32_t(r[k][c]) + r[k][4 + c];
      out[c] = std::uint8_t((s + 4) >> 3);
    }
  } else {
    for (int c = 0; c < 3; ++c) {
      std::uint32_t s = 0;
      for (int k = 0; k < 4; ++k)
        s += std::uint32_t(r[k][c]) * r[k][3] + std::uint32_t(r[k][4 + c]) * r[k][7];
      out[c] = std::uint8_t((2 * s + sum_a) / (2 * sum_a));  // round_div, non-negative
    }
  }
  out[3] = std::uint8_t((sum_a + 4) >> 3);
}

template <typename T>
inline T majority8(const T* const r[4]) {
  const T v = r[0][0];
  if (r[0][1] == v && r[1][0] == v && r[1][1] == v && r[2][0] == v && r[2][1] == v &&
      r[3][0] == v && r[3][1] == v) {
    return v;
  }
  std::uint16_t c[8];
  for (int k = 0; k < 4; ++k) {
    c[2 * k] = r[k][0];
    c[2 * k + 1] = r[k][1];
  }
  return T(reduce_majority(c, 8));
}

// Reduces output voxels [0, full_x) of a row whose children all exist, from the four source rows
// of their children (rows 2y and 2y + 1 of both slices, each from its first child's voxel on);
// the caller handles the rest.
void downsample_row_full(ChannelType type, const std::uint8_t* const rows[4], std::int64_t full_x,
                         std::uint8_t* dst) {
  switch (type) {
    case ChannelType::kRgba8:
      for (std::int64_t x = 0; x < full_x; ++x) {
        const std::uint8_t* r[4];
        for (int k = 0; k < 4; ++k)
          r[k] = rows[k] + 8 * x;
        // Eight equal children (outside the body, most of a slice) reduce to themselves:
        // reduce8_rgba gives (8 v + 4) >> 3 = v for every component.
        std::uint64_t pair[4];
        for (int k = 0; k < 4; ++k)
          std::memcpy(&pair[k], r[k], 8);
        if (pair[0] == pair[1] && pair[0] == pair[2] && pair[0] == pair[3] &&
            std::memcmp(r[0], r[0] + 4, 4) == 0) {
          std::memcpy(dst + 4 * x, r[0], 4);
          continue;
        }
        reduce8_rgba(r, dst + 4 * x);
      }
      break;
    case ChannelType::kInt16:
      for (std::int64_t x = 0; x < full_x; ++x) {
        std::int32_t s = 0;
        for (int k = 0; k < 4; ++k) {
          std::int16_t v[2];
          std::memcpy(v, rows[k] + 4 * x, 4);
          s += std::int32_t(v[0]) + v[1];
        }
        const std::int16_t m = std::int16_t((s + 4) >> 3);
        std::memcpy(dst + 2 * x, &m, 2);
      }
      break;
    case ChannelType::kUint8:
      for (std::int64_t x = 0; x < full_x; ++x) {
        const std::uint8_t* r[4];
        for (int k = 0; k < 4; ++k)
          r[k] = rows[k] + 2 * x;
        dst[x] = majority8(r);
      }
      break;
    case ChannelType::kUint16:
      for (std::int64_t x = 0; x < full_x; ++x) {
        std::uint16_t c[4][2];
        const std::uint16_t* r[4];
        for (int k = 0; k < 4; ++k) {
          std::memcpy(c[k], rows[k] + 4 * x, 4);
          r[k] = c[k];
        }
        const std::uint16_t m = majority8(r);
        std::memcpy(dst + 2 * x, &m, 2);
      }
      break;
  }
}

}  // namespace

void downsample_slice(ChannelType type, const std::uint8_t* src, int nzc, std::int64_t dx,
                      std::int64_t dy, std::uint8_t* dst, int threads,
                      const ZeroPagedBuffer* zeros) {
  const std::int64_t ox = ceil_div(dx, 2), oy = ceil_div(dy, 2);
  const std::size_t bytes = channel_type_bytes(type);
  const std::size_t row_bytes = std::size_t(dx) * bytes;
  const std::size_t plane = row_bytes * std::size_t(dy);
  // Output voxels per run whose children span one page of each source row.
  const std::int64_t run =
      std::max<std::int64_t>(1, std::int64_t(ZeroPagedBuffer::page_size() / (2 * bytes)));
  // Children of one run in pages known to be zero are read from here instead.
  const std::vector<std::uint8_t> zero_run(zeros ? std::size_t(2 * run) * bytes : 0, 0);
  auto row = [&](std::int64_t y) {
    std::uint8_t* out = dst + std::size_t(y) * std::size_t(ox) * bytes;
    std::int64_t x = 0;
    if (nzc == 2 && 2 * y + 1 < dy) {
      x = dx / 2;  // output voxels with both x children
      const std::uint8_t* base = src + std::size_t(2 * y) * row_bytes;
      const std::uint8_t* rows[4] = {base, base + row_bytes, base + plane,
                                     base + plane + row_bytes};
      if (!zeros) {
        downsample_row_full(type, rows, x, out);
      } else {
        for (std::int64_t x0 = 0; x0 < x; x0 += run) {
          const std::int64_t x1 = std::min(x, x0 + run);
          const std::size_t from = std::size_t(2 * x0) * bytes;
          const std::size_t n = std::size_t(2 * (x1 - x0)) * bytes;
          const std::uint8_t* run_rows[4];
          int zero_rows = 0;
          for (int k = 0; k < 4; ++k) {
            const bool zero = zeros->known_zero(rows[k] + from, n);
            run_rows[k] = zero ? zero_run.data() : rows[k] + from;
            zero_rows += zero;
          }
          std::uint8_t* run_out = out + std::size_t(x0) * bytes;
          if (zero_rows == 4)
            std::memset(run_out, 0, std::size_t(x1 - x0) * bytes);
          else
            downsample_row_full(type, run_rows, x1 - x0, run_out);
        }
      }
    }
    for (; x < ox; ++x)
      reduce_generic(type, src, nzc, dx, dy, x, y, out + std::size_t(x) * bytes);
  };
  if (ox * oy < 65536 || threads <= 1) {
    for (std::int64_t y = 0; y < oy; ++y)
      row(y);
  } else {
    const std::int64_t chunk = 16;
    parallel_for(ceil_div(oy, chunk), threads, [&](std::int64_t i) {
      for (std::int64_t y = i * chunk; y < std::min(oy, (i + 1) * chunk); ++y)
        row(y);
    });
  }
}

}  // namespace vispack::format

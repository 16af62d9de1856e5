// Reader::Impl: payload I/O, a brick decoded, a region copied out of its bricks (reader_impl.h).
#include "vispack/format/reader.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>
#include <xxhash.h>
#include <zstd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <limits>
#include <mutex>
#include <stdexcept>

#include "layout.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"
#include "vispack/format/metadata.h"

#include "reader_impl.h"

namespace vispack::format {

using namespace detail;
using nlohmann::json;

ZSTD_DCtx* Reader::Impl::acquire() const {
  {
    std::lock_guard<std::mutex> lock(dctx_mutex);
    if (!dctx_free.empty()) {
      ZSTD_DCtx* d = dctx_free.back();
      dctx_free.pop_back();
      return d;
    }
  }
  ZSTD_DCtx* d = ZSTD_createDCtx();
  if (!d) throw std::bad_alloc();
  return d;
}

void Reader::Impl::release(ZSTD_DCtx* d) const {
  std::lock_guard<std::mutex> lock(dctx_mutex);
  dctx_free.push_back(d);
}

void Reader::Impl::decode(const BrickInfo& b, void* out, std::size_t out_size,
                          bool verify_checksum) const {
  const std::size_t n = brick_bytes(b.channel);
  if (out_size < n)
    throw std::invalid_argument(
        cat(path, ": ", name(b), ": output buffer of ", out_size, " bytes, need ", n));
  const std::uint8_t* payload = base + b.offset;
  if (verify_checksum && b.codec != Codec::kUniform) {
    std::uint64_t sum = xxh64(payload, std::size_t(b.stored_size));
    if (sum != b.checksum)
      fail_brick(DefectKind::kPayloadChecksum, b,
                 cat("payload checksum mismatch (stored ", hex64(b.checksum), ", computed ",
                     hex64(sum), ")"));
  }
  switch (b.codec) {
    case Codec::kUniform: {
      const std::size_t vb = channel_type_bytes(channels[std::size_t(b.channel)].type);
      auto* o = static_cast<std::uint8_t*>(out);
      if (vb == 1) {
        std::memset(o, b.uniform[0], n);
      } else {
        for (std::size_t i = 0; i < n; i += vb)
          std::memcpy(o + i, b.uniform.data(), vb);
      }
      break;
    }
    case Codec::kRaw:
      std::memcpy(out, payload, n);
      break;
    case Codec::kZstd: {
      ZSTD_DCtx* d = acquire();
      std::size_t r = ZSTD_decompressDCtx(d, out, n, payload, std::size_t(b.stored_size));
      release(d);
      if (ZSTD_isError(r))
        fail_brick(DefectKind::kPayloadDecode, b,
                   cat("zstd payload does not decode: ", ZSTD_getErrorName(r)));
      if (r != n)
        fail_brick(DefectKind::kPayloadDecode, b,
                   cat("zstd payload decodes to ", r, " bytes, expected ", n));
      break;
    }
  }
}

const LevelInfo& Reader::Impl::checked_level(int level, int channel) const {
  if (level < 0 || level >= int(levels.size()))
    throw std::out_of_range(cat(path, ": level ", level, " outside [0, ", levels.size(), ")"));
  if (channel < 0 || channel >= int(channels.size()))
    throw std::out_of_range(
        cat(path, ": channel ", channel, " outside [0, ", channels.size(), ")"));
  return levels[std::size_t(level)];
}

const BrickInfo& Reader::Impl::brick(int channel, int level, std::int64_t bx, std::int64_t by,
                                     std::int64_t bz) const {
  const LevelInfo& li = checked_level(level, channel);
  if (bx < 0 || by < 0 || bz < 0 || bx >= li.bricks[0] || by >= li.bricks[1] ||
      bz >= li.bricks[2]) {
    throw std::out_of_range(
        cat(path, ": brick (", bx, ",", by, ",", bz, ") outside the level ", level, " grid"));
  }
  return bricks[std::size_t(geometry.entry(level, channel, bx, by, bz))];
}

void Reader::Impl::copy_brick(const BrickInfo& b, const std::array<std::int64_t, 3>& o,
                              const std::array<std::int64_t, 3>& n, std::uint8_t* out,
                              std::vector<std::uint8_t>& tmp) const {
  const std::size_t vb = channel_type_bytes(channels[std::size_t(b.channel)].type);
  const std::int64_t e = edge;
  std::array<std::int64_t, 3> lo{}, hi{};
  for (int a = 0; a < 3; ++a) {
    lo[a] = std::max(o[a], b.brick[a] * e);
    hi[a] = std::min(o[a] + n[a], (b.brick[a] + 1) * e);
  }
  const std::size_t row = std::size_t(hi[0] - lo[0]) * vb;
  if (b.codec == Codec::kUniform) {
    for (std::int64_t z = lo[2]; z < hi[2]; ++z) {
      for (std::int64_t y = lo[1]; y < hi[1]; ++y) {
        std::uint8_t* dst = out + (std::size_t((z - o[2]) * n[1] + (y - o[1])) * std::size_t(n[0]) +
                                   std::size_t(lo[0] - o[0])) *
                                      vb;
        if (vb == 1)
          std::memset(dst, b.uniform[0], row);
        else
          for (std::size_t i = 0; i < row; i += vb)
            std::memcpy(dst + i, b.uniform.data(), vb);
      }
    }
    return;
  }
  const std::uint8_t* src = nullptr;
  if (b.codec == Codec::kRaw) {
    src = base + b.offset;
  } else {
    tmp.resize(brick_bytes(b.channel));
    decode(b, tmp.data(), tmp.size(), false);
    src = tmp.data();
  }
  for (std::int64_t z = lo[2]; z < hi[2]; ++z) {
    for (std::int64_t y = lo[1]; y < hi[1]; ++y) {
      const std::uint8_t* s =
          src + (std::size_t(((z - b.brick[2] * e) * e + (y - b.brick[1] * e)) * e +
                             (lo[0] - b.brick[0] * e))) *
                    vb;
      std::uint8_t* dst = out + (std::size_t((z - o[2]) * n[1] + (y - o[1])) * std::size_t(n[0]) +
                                 std::size_t(lo[0] - o[0])) *
                                    vb;
      std::memcpy(dst, s, row);
    }
  }
}

void Reader::Impl::region(int channel, int level, const std::array<std::int64_t, 3>& o,
                          const std::array<std::int64_t, 3>& n, void* out, int threads) const {
  const LevelInfo& li = checked_level(level, channel);
  for (int a = 0; a < 3; ++a) {
    if (o[a] < 0 || n[a] < 0 || o[a] > li.dims[a] || n[a] > li.dims[a] - o[a]) {
      throw std::out_of_range(cat(path, ": region [", o[0], ",", o[1], ",", o[2], "] + [", n[0],
                                  ",", n[1], ",", n[2], "] is not inside level ", level, " (",
                                  li.dims[0], "x", li.dims[1], "x", li.dims[2], ")"));
    }
  }
  if (n[0] == 0 || n[1] == 0 || n[2] == 0) return;
  std::array<std::int64_t, 3> b0{}, b1{};
  for (int a = 0; a < 3; ++a) {
    b0[a] = o[a] / edge;
    b1[a] = (o[a] + n[a] - 1) / edge + 1;
  }
  const std::int64_t cx = b1[0] - b0[0], cy = b1[1] - b0[1], cz = b1[2] - b0[2];
  auto* dst = static_cast<std::uint8_t*>(out);
  if (threads == 1 || cx * cy * cz == 1) {
    std::vector<std::uint8_t> tmp;
    for (std::int64_t bz = b0[2]; bz < b1[2]; ++bz)
      for (std::int64_t by = b0[1]; by < b1[1]; ++by)
        for (std::int64_t bx = b0[0]; bx < b1[0]; ++bx)
          copy_brick(brick(channel, level, bx, by, bz), o, n, dst, tmp);
    return;
  }
  parallel_for(cx * cy * cz, threads, [&](std::int64_t i) {
    std::vector<std::uint8_t> tmp;
    std::int64_t bx = b0[0] + i % cx, by = b0[1] + (i / cx) % cy, bz = b0[2] + i / (cx * cy);
    copy_brick(brick(channel, level, bx, by, bz), o, n, dst, tmp);
  });
}

}  // namespace vispack::format

#include "vispack/format/writer.h"

#include <xxhash.h>
#include <zstd.h>

#include <algorithm>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <exception>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <unordered_set>
#include <utility>

#include "layout.h"
#include "spill_store.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"
#include "vispack/common/zero_paged_buffer.h"
#include "vispack/format/downsample.h"
#include "vispack/format/geometry.h"
#include "vispack/format/limits.h"
#include "vispack/format/metadata.h"

namespace vispack::format {
namespace {

using detail::align_up;
using detail::IndexEntry;

constexpr std::int64_t kMaxDim = (std::int64_t(1) << 31) - 1;

bool is_power_of_two(int v) {
  return v > 0 && (v & (v - 1)) == 0;
}

std::int64_t ceil_div(std::int64_t a, std::int64_t b) {
  return (a + b - 1) / b;
}

// Per-thread state of a compression worker: its zstd context and scratch buffers, allocated
// once and reused for every brick (no per-brick allocation or zero-filling).
struct WorkerScratch {
  ZSTD_CCtx* cctx = nullptr;
  std::vector<std::uint8_t> brick;      // the gathered, padded brick
  std::vector<std::uint8_t> out;        // zstd output (compress bound of one brick)
  std::vector<std::uint8_t> seen;       // uint16 label presence, all 0 between bricks
  std::vector<std::uint32_t> ids_seen;  // IDs set in `seen`, to reset them

  WorkerScratch() {
    cctx = ZSTD_createCCtx();
    if (!cctx) throw std::bad_alloc();
  }
  ~WorkerScratch() { ZSTD_freeCCtx(cctx); }
  WorkerScratch(const WorkerScratch&) = delete;
  WorkerScratch& operator=(const WorkerScratch&) = delete;
};

struct BrickResult {
  IndexEntry entry{};
  // Stored bytes (empty for uniform): allocated to size and copied into (assign from a range
  // does not zero them first), moved on to an EncodedBrick as they are.
  std::vector<std::uint8_t> payload;
  std::vector<std::uint32_t> labels;
};

// Stats over a whole (padded) brick: the padding replicates valid voxels, so the minimum,
// maximum and label set equal those of the valid voxels alone.
void brick_stats(ChannelType type, const std::uint8_t* data, std::size_t voxels, IndexEntry& e,
                 std::vector<std::uint32_t>& labels, WorkerScratch& scratch) {
  std::memset(e.min, 0, 8);
  std::memset(e.max, 0, 8);
  switch (type) {
    case ChannelType::kRgba8: {
      std::uint8_t lo[4] = {255, 255, 255, 255}, hi[4] = {0, 0, 0, 0};
      for (std::size_t i = 0; i < voxels; ++i) {
        for (int c = 0; c < 4; ++c) {
          std::uint8_t v = data[4 * i + c];
          lo[c] = std::min(lo[c], v);
          hi[c] = std::max(hi[c], v);
        }
      }
      std::memcpy(e.min, lo, 4);
      std::memcpy(e.max, hi, 4);
      break;
    }
    case ChannelType::kInt16: {
      const auto* v = reinterpret_cast<const std::int16_t*>(data);
      std::int16_t lo = std::numeric_limits<std::int16_t>::max();
      std::int16_t hi = std::numeric_limits<std::int16_t>::min();
      for (std::size_t i = 0; i < voxels; ++i) {
        lo = std::min(lo, v[i]);
        hi = std::max(hi, v[i]);
      }
      std::memcpy(e.min, &lo, 2);
      std::memcpy(e.max, &hi, 2);
      break;
    }
    case ChannelType::kUint8: {
      bool seen[256] = {};
      for (std::size_t i = 0; i < voxels; ++i)
        seen[data[i]] = true;
      for (int id = 0; id < 256; ++id) {
        if (seen[id]) labels.push_back(std::uint32_t(id));
      }
      std::uint8_t lo = std::uint8_t(labels.front()), hi = std::uint8_t(labels.back());
      std::memcpy(e.min, &lo, 1);
      std::memcpy(e.max, &hi, 1);
      break;
    }
    case ChannelType::kUint16: {
      const auto* v = reinterpret_cast<const std::uint16_t*>(data);
      std::vector<std::uint8_t>& seen = scratch.seen;
      std::vector<std::uint32_t>& ids = scratch.ids_seen;
      if (seen.empty()) seen.assign(65536, 0);
      ids.clear();
      std::uint16_t last = v[0];
      seen[last] = 1;
      ids.push_back(last);
      for (std::size_t i = 1; i < voxels; ++i) {
        if (v[i] == last) continue;  // runs are the common case in label volumes
        last = v[i];
        if (!seen[last]) {
          seen[last] = 1;
          ids.push_back(last);
        }
      }
      std::sort(ids.begin(), ids.end());
      for (std::uint32_t id : ids)
        seen[id] = 0;
      labels.assign(ids.begin(), ids.end());
      std::uint16_t lo = std::uint16_t(labels.front()), hi = std::uint16_t(labels.back());
      std::memcpy(e.min, &lo, 2);
      std::memcpy(e.max, &hi, 2);
      break;
    }
  }
}

void validate(const WriterOptions& o) {
  for (int a = 0; a < 3; ++a) {
    if (o.dims[a] < 1 || o.dims[a] > kMaxDim) {
      throw std::invalid_argument(
          cat("WriterOptions.dims[", a, "] = ", o.dims[a], " is outside [1, 2^31 - 1]"));
    }
    if (!(o.spacing_mm[a] > 0) || !std::isfinite(o.spacing_mm[a])) {
      throw std::invalid_argument(
          cat("WriterOptions.spacing_mm[", a, "] = ", o.spacing_mm[a], " must be finite and > 0"));
    }
    if (!std::isfinite(o.origin_mm[a])) {
      throw std::invalid_argument(cat("WriterOptions.origin_mm[", a, "] is not finite"));
    }
  }
  if (!is_power_of_two(o.brick_edge) || o.brick_edge < 4 || o.brick_edge > 1024) {
    throw std::invalid_argument(
        cat("WriterOptions.brick_edge = ", o.brick_edge, " must be a power of two in [4, 1024]"));
  }
  if (o.zstd_level < ZSTD_minCLevel() || o.zstd_level > ZSTD_maxCLevel() || o.zstd_level == 0) {
    throw std::invalid_argument(cat("WriterOptions.zstd_level = ", o.zstd_level, " must be in [",
                                    ZSTD_minCLevel(), ", ", ZSTD_maxCLevel(), "] and not 0"));
  }
  if (o.channels.empty() || o.channels.size() > 16) {
    throw std::invalid_argument(
        cat("WriterOptions.channels has ", o.channels.size(), " entries; 1 to 16 are allowed"));
  }
  std::unordered_set<std::string> names;
  for (const auto& c : o.channels) {
    if (c.name.empty() || c.name.size() > 255) {
      throw std::invalid_argument("WriterOptions.channels: a channel name is empty or too long");
    }
    if (!names.insert(c.name).second) {
      throw std::invalid_argument(
          cat("WriterOptions.channels: duplicate channel \"", c.name, "\""));
    }
    channel_type_bytes(c.type);  // throws on a bad enum value
  }
  std::unordered_set<std::uint32_t> ids;
  for (const auto& l : o.label_table) {
    if (l.id == 0 || l.id > 65535) {
      throw std::invalid_argument(
          cat("WriterOptions.label_table: id ", l.id, " (\"", l.name, "\") is outside [1, 65535]"));
    }
    if (!ids.insert(l.id).second) {
      throw std::invalid_argument(cat("WriterOptions.label_table: duplicate id ", l.id));
    }
  }
  if (!o.extra_metadata.is_object() && !o.extra_metadata.is_null()) {
    throw std::invalid_argument("WriterOptions.extra_metadata must be a JSON object");
  }
  // One slab of level 0 must be addressable.
  const std::uint64_t plane = std::uint64_t(o.dims[0]) * std::uint64_t(o.dims[1]);
  if (plane > (std::uint64_t(1) << 40) / std::uint64_t(o.brick_edge)) {
    throw std::invalid_argument(cat("WriterOptions.dims: a slab of ", o.brick_edge, " slices of ",
                                    o.dims[0], "x", o.dims[1], " voxels is too large"));
  }
}

// Where the bricks of one slab come from: slab `bz` of level `level` (its first `nzv` slices
// valid), in a level of dx * dy voxels per slice and gx * gy bricks per slab and channel.
struct BrickSource {
  int level = 0;
  std::int64_t bz = 0;
  int nzv = 0;
  std::int64_t gx = 0, gy = 0, dx = 0, dy = 0;
};

// The voxels of one channel a brick is gathered from: planes of `rows` rows (rows
// [y_first, y_first + rows) of the level, all dx voxels wide), one plane per slice of the slab.
struct ChannelBlock {
  const std::uint8_t* data = nullptr;
  std::int64_t y_first = 0;
  std::int64_t rows = 0;
  // The buffer `data` lies in when it knows which of its pages hold only zeros (the level-0
  // slab): rows in such pages are gathered as zeros without being read (never faulted in).
  const ZeroPagedBuffer* zeros = nullptr;
};

// Makes brick `i` (index order within the slab: channel, by, bx) of `src` from `block`, the
// brick's channel (its rows must cover the brick's): gathers and pads it, computes its stats and
// encodes it (SPEC.md "Codecs"). The one encoder of the Writer and encode_level0_slab.
void encode_brick(const WriterOptions& opt, const std::vector<ChannelSpec>& stored,
                  const std::string& path, const BrickSource& source, const ChannelBlock& block,
                  std::int64_t i, WorkerScratch& scratch, BrickResult& r) {
  const int L = source.level;
  const std::int64_t per_channel = source.gx * source.gy;
  const int c = int(i / per_channel);
  const std::int64_t bx = (i % per_channel) % source.gx, by = (i % per_channel) / source.gx;
  const std::int64_t bz = source.bz;
  const int nzv = source.nzv;
  const std::int64_t e = opt.brick_edge;
  const ChannelType type = stored[c].type;
  const std::size_t bytes = channel_type_bytes(type);
  const std::int64_t dx = source.dx, dy = source.dy;
  const std::int64_t x0 = bx * e, y0 = by * e;
  const std::int64_t nxv = std::min(e, dx - x0), nyv = std::min(e, dy - y0);
  const std::size_t row_bytes = std::size_t(e) * bytes;
  const std::size_t plane_bytes = row_bytes * std::size_t(e);
  const std::size_t brick_bytes = plane_bytes * std::size_t(e);
  if (scratch.brick.size() < brick_bytes) scratch.brick.resize(brick_bytes);
  std::uint8_t* buf = scratch.brick.data();
  const std::uint8_t* slab = block.data;
  for (std::int64_t z = 0; z < e; ++z) {
    std::uint8_t* plane = buf + std::size_t(z) * plane_bytes;
    if (z >= nzv) {
      std::memcpy(plane, buf + std::size_t(nzv - 1) * plane_bytes, plane_bytes);
      continue;
    }
    for (std::int64_t y = 0; y < e; ++y) {
      std::uint8_t* dst = plane + std::size_t(y) * row_bytes;
      if (y >= nyv) {
        std::memcpy(dst, plane + std::size_t(nyv - 1) * row_bytes, row_bytes);
        continue;
      }
      const std::uint8_t* src =
          slab + ((std::size_t(z) * block.rows + (y0 + y - block.y_first)) * dx + x0) * bytes;
      const std::size_t n = std::size_t(nxv) * bytes;
      if (block.zeros && block.zeros->known_zero(src, n))
        std::memset(dst, 0, n);
      else
        std::memcpy(dst, src, n);
      for (std::int64_t x = nxv; x < e; ++x) {
        std::memcpy(dst + std::size_t(x) * bytes, dst + std::size_t(nxv - 1) * bytes, bytes);
      }
    }
  }
  IndexEntry& en = r.entry;
  en.bx = std::uint32_t(bx);
  en.by = std::uint32_t(by);
  en.bz = std::uint32_t(bz);
  en.level = std::uint8_t(L);
  en.channel = std::uint8_t(c);
  brick_stats(type, buf, brick_bytes / bytes, en, r.labels, scratch);
  if (std::memcmp(en.min, en.max, 8) == 0) {
    en.codec = std::uint8_t(Codec::kUniform);
    return;  // offset, size, checksum stay 0
  }
  en.codec = std::uint8_t(Codec::kRaw);
  const std::uint8_t* stored_bytes = buf;
  std::size_t stored_size = brick_bytes;
  if (opt.compress) {
    const std::size_t bound = ZSTD_compressBound(brick_bytes);
    if (scratch.out.size() < bound) scratch.out.resize(bound);
    std::size_t n = ZSTD_compressCCtx(scratch.cctx, scratch.out.data(), bound, buf, brick_bytes,
                                      opt.zstd_level);
    if (ZSTD_isError(n)) {
      throw Error(cat(path, ": zstd failed on brick level ", L, " channel ", stored[c].name, " (",
                      bx, ",", by, ",", bz, "): ", ZSTD_getErrorName(n)));
    }
    if (n < brick_bytes) {
      stored_bytes = scratch.out.data();
      stored_size = n;
      en.codec = std::uint8_t(Codec::kZstd);
    }
  }
  r.payload.assign(stored_bytes, stored_bytes + stored_size);
  en.stored_size = stored_size;
  en.checksum = xxh64(stored_bytes, stored_size);
}

// Throws InputError unless every ID of a uint16 label slice fits uint8 (the stored type); `what`,
// `slice` and `channel` name the slice in the error.
void check_labels_fit_uint8(const std::uint16_t* src, std::size_t plane, std::int64_t nx,
                            const std::string& what, std::int64_t slice,
                            const std::string& channel) {
  std::uint16_t any_high = 0;
  for (std::size_t i = 0; i < plane; ++i)
    any_high |= std::uint16_t(src[i] & 0xFF00u);
  if (any_high) {
    for (std::size_t i = 0; i < plane; ++i) {
      if (src[i] > 255) {
        throw InputError(cat(what, ": slice ", slice, ", channel \"", channel, "\", voxel (",
                             i % std::size_t(nx), ", ", i / std::size_t(nx), "): label ID ", src[i],
                             " does not fit the stored type uint8"));
      }
    }
  }
}

// Narrows a uint16 label slice to uint8, refusing IDs above 255 (checked first: `dst` is untouched
// on error).
void narrow_labels(const std::uint16_t* src, std::size_t plane, std::int64_t nx, std::uint8_t* dst,
                   const std::string& what, std::int64_t slice, const std::string& channel) {
  check_labels_fit_uint8(src, plane, nx, what, slice, channel);
  for (std::size_t i = 0; i < plane; ++i)
    dst[i] = std::uint8_t(src[i]);
}

}  // namespace

std::vector<ChannelSpec> stored_channels_for(const WriterOptions& options) {
  std::uint32_t max_id = 0;
  for (const auto& l : options.label_table)
    max_id = std::max(max_id, l.id);
  std::vector<ChannelSpec> stored;
  for (const auto& c : options.channels) {
    ChannelSpec s = c;
    if (is_label_type(c.type) && !options.label_table.empty()) {
      s.type = max_id <= 255 ? ChannelType::kUint8 : ChannelType::kUint16;
    }
    stored.push_back(s);
  }
  return stored;
}

std::int64_t level0_slab_count(const WriterOptions& options) {
  return ceil_div(options.dims[2], options.brick_edge);
}

std::vector<EncodedBrick> encode_level0_slab(const WriterOptions& options, std::int64_t bz,
                                             const std::vector<const void*>& channel_slabs,
                                             std::vector<std::vector<std::uint8_t>>* level1,
                                             SlabLabels labels) {
  Level1SliceSink sink;
  if (level1) {
    level1->assign(stored_channels_for(options).size(), {});
    sink = [level1](std::size_t c, int, const std::uint8_t* slice, std::size_t bytes) {
      (*level1)[c].insert((*level1)[c].end(), slice, slice + bytes);
    };
  }
  return encode_level0_slab(options, bz, channel_slabs, sink, labels, {});
}

namespace {

// The stored bytes of each channel of a level-0 slab of `nzv` slices: the caller's slab itself,
// or (uint8 labels handed over as uint16, SlabLabels::kUint16) a narrowed copy. No other copy: a
// level-0 slab of 2048x1216 slices is ~1 GB. `zeros`: the caller's zero-page buffer of each
// channel passed on (none for a narrowed copy).
struct SlabChannels {
  std::vector<std::vector<std::uint8_t>> narrowed;
  std::vector<const std::uint8_t*> slabs;
  std::vector<const ZeroPagedBuffer*> zeros;
};

SlabChannels slab_channels(const std::vector<ChannelSpec>& stored, std::int64_t bz, std::int64_t e,
                           int nzv, std::int64_t dx, std::size_t plane,
                           const std::vector<const void*>& channel_slabs, SlabLabels labels,
                           const std::vector<const ZeroPagedBuffer*>& zero_pages) {
  SlabChannels out;
  out.narrowed.resize(stored.size());
  out.slabs.resize(stored.size());
  out.zeros.assign(stored.size(), nullptr);
  for (std::size_t c = 0; c < stored.size(); ++c) {
    if (!channel_slabs[c]) {
      throw std::invalid_argument(
          cat("encode_level0_slab: null pointer for channel \"", stored[c].name, "\""));
    }
    if (stored[c].type == ChannelType::kUint8 && labels == SlabLabels::kUint16) {
      out.narrowed[c].resize(plane * std::size_t(nzv));
      const auto* src = static_cast<const std::uint16_t*>(channel_slabs[c]);
      for (int z = 0; z < nzv; ++z)
        narrow_labels(src + std::size_t(z) * plane, plane, dx,
                      out.narrowed[c].data() + std::size_t(z) * plane, "encode_level0_slab",
                      bz * e + z, stored[c].name);
      out.slabs[c] = out.narrowed[c].data();
    } else {
      out.slabs[c] = static_cast<const std::uint8_t*>(channel_slabs[c]);
      if (!zero_pages.empty()) out.zeros[c] = zero_pages[c];
    }
  }
  return out;
}

// The slab's level-1 slices, reduced as Writer::Impl::push reduces them (pairs of slices; the
// volume's last slice alone when dims[2] is odd), one at a time into one slice's buffer, handed
// to `level1`. Slabs start at even slices (even edge).
void reduce_slab_to_level1(const WriterOptions& options, const std::vector<ChannelSpec>& stored,
                           const SlabChannels& channels, int nzv, std::int64_t dx, std::int64_t dy,
                           const Level1SliceSink& level1) {
  const std::size_t plane = std::size_t(dx) * std::size_t(dy);
  const std::int64_t hx = ceil_div(dx, 2), hy = ceil_div(dy, 2);
  const int n1 = int(ceil_div(nzv, 2));
  std::vector<std::uint8_t> slice;
  for (std::size_t c = 0; c < stored.size(); ++c) {
    const std::size_t bytes = channel_type_bytes(stored[c].type);
    const std::size_t slice_bytes = std::size_t(hx) * std::size_t(hy) * bytes;
    if (slice.size() < slice_bytes) slice.resize(slice_bytes);
    for (int k = 0; k < n1; ++k) {
      downsample_slice(stored[c].type, channels.slabs[c] + std::size_t(2 * k) * plane * bytes,
                       std::min(2, nzv - 2 * k), dx, dy, slice.data(),
                       resolve_threads(options.threads), channels.zeros[c]);
      level1(c, k, slice.data(), slice_bytes);
    }
  }
}

// The encoded bricks as the caller receives them (their payloads and label sets moved out).
std::vector<EncodedBrick> to_encoded_bricks(std::vector<BrickResult>& results) {
  std::vector<EncodedBrick> out(results.size());
  for (std::size_t i = 0; i < out.size(); ++i) {
    const IndexEntry& en = results[i].entry;
    EncodedBrick& b = out[i];
    b.codec = Codec(en.codec);
    std::memcpy(b.min.data(), en.min, 8);
    std::memcpy(b.max.data(), en.max, 8);
    b.checksum = en.checksum;
    b.payload = std::move(results[i].payload);
    b.labels = std::move(results[i].labels);
  }
  return out;
}

}  // namespace

std::vector<EncodedBrick> encode_level0_slab(
    const WriterOptions& options, std::int64_t bz, const std::vector<const void*>& channel_slabs,
    const Level1SliceSink& level1, SlabLabels labels,
    const std::vector<const ZeroPagedBuffer*>& zero_pages) {
  validate(options);
  const std::vector<ChannelSpec> stored = stored_channels_for(options);
  const std::int64_t e = options.brick_edge;
  if (bz < 0 || bz >= level0_slab_count(options)) {
    throw std::invalid_argument(
        cat("encode_level0_slab: slab ", bz, " is outside [0, ", level0_slab_count(options), ")"));
  }
  if (channel_slabs.size() != stored.size()) {
    throw std::invalid_argument(cat("encode_level0_slab: got ", channel_slabs.size(),
                                    " channel pointers, expected ", stored.size()));
  }
  if (!zero_pages.empty() && zero_pages.size() != stored.size()) {
    throw std::invalid_argument(cat("encode_level0_slab: got ", zero_pages.size(),
                                    " zero-page buffers, expected ", stored.size()));
  }
  const int nzv = int(std::min(e, options.dims[2] - bz * e));
  const std::int64_t dx = options.dims[0], dy = options.dims[1];
  const std::size_t plane = std::size_t(dx) * std::size_t(dy);
  const SlabChannels channels =
      slab_channels(stored, bz, e, nzv, dx, plane, channel_slabs, labels, zero_pages);
  const std::int64_t gx = ceil_div(dx, e), gy = ceil_div(dy, e);
  const std::int64_t items = gx * gy * std::int64_t(stored.size());
  std::vector<BrickResult> results(static_cast<std::size_t>(items));
  const BrickSource source{0, bz, nzv, gx, gy, dx, dy};
  const int threads = int(std::min<std::int64_t>(resolve_threads(options.threads), items));
  parallel_for(threads, threads, [&](std::int64_t t) {
    WorkerScratch scratch;
    for (std::int64_t i = t; i < items; i += threads) {
      const std::size_t c = std::size_t(i / (gx * gy));
      encode_brick(options, stored, "encode_level0_slab", source,
                   ChannelBlock{channels.slabs[c], 0, dy, channels.zeros[c]}, i, scratch,
                   results[std::size_t(i)]);
    }
  });
  if (level1 && format::level_count_for(options.dims, int(e)) > 1)
    reduce_slab_to_level1(options, stored, channels, nzv, dx, dy, level1);
  return to_encoded_bricks(results);
}

void decode_encoded_brick(const EncodedBrick& brick, ChannelType stored, int brick_edge,
                          std::uint8_t* out, const std::string& what) {
  const std::size_t bytes = channel_type_bytes(stored);
  const std::size_t n =
      std::size_t(brick_edge) * std::size_t(brick_edge) * std::size_t(brick_edge) * bytes;
  switch (brick.codec) {
    case Codec::kUniform:
      for (std::size_t i = 0; i < n; i += bytes)
        std::memcpy(out + i, brick.min.data(), bytes);
      return;
    case Codec::kRaw:
    case Codec::kZstd:
      break;
    default:
      throw FormatError(cat(what, ": unknown codec ", int(brick.codec)));
  }
  if (xxh64(brick.payload.data(), brick.payload.size()) != brick.checksum)
    throw FormatError(cat(what, ": payload checksum mismatch"));
  if (brick.codec == Codec::kRaw) {
    if (brick.payload.size() != n)
      throw FormatError(
          cat(what, ": raw payload of ", brick.payload.size(), " bytes, expected ", n));
    std::memcpy(out, brick.payload.data(), n);
    return;
  }
  std::size_t r = ZSTD_decompress(out, n, brick.payload.data(), brick.payload.size());
  if (ZSTD_isError(r))
    throw FormatError(cat(what, ": zstd payload does not decode: ", ZSTD_getErrorName(r)));
  if (r != n) throw FormatError(cat(what, ": zstd payload decodes to ", r, " bytes, expected ", n));
}

std::vector<std::uint8_t> compress_bytes(const void* data, std::size_t size, int level) {
  // Into an uninitialised buffer of the compress bound (a vector of that size would be zeroed
  // first: its pages all faulted in for a frame that is mostly far smaller), then copied out.
  const std::size_t bound = ZSTD_compressBound(size);
  std::unique_ptr<std::uint8_t[]> buffer(new std::uint8_t[bound]);
  const std::size_t n = ZSTD_compress(buffer.get(), bound, data, size, level);
  if (ZSTD_isError(n)) throw Error(cat("zstd compression failed: ", ZSTD_getErrorName(n)));
  return std::vector<std::uint8_t>(buffer.get(), buffer.get() + n);
}

ZstdFrameWriter::ZstdFrameWriter(std::uint64_t size, int level) : left_(size) {
  cctx_ = ZSTD_createCCtx();
  if (!cctx_) throw std::bad_alloc();
  std::size_t r = ZSTD_CCtx_setParameter(cctx_, ZSTD_c_compressionLevel, level);
  if (!ZSTD_isError(r)) r = ZSTD_CCtx_setPledgedSrcSize(cctx_, size);
  if (ZSTD_isError(r)) {
    ZSTD_freeCCtx(cctx_);
    throw Error(cat("zstd frame setup failed: ", ZSTD_getErrorName(r)));
  }
}

ZstdFrameWriter::~ZstdFrameWriter() {
  ZSTD_freeCCtx(cctx_);
}

void ZstdFrameWriter::write(const void* data, std::size_t n) {
  if (n > left_)
    throw std::invalid_argument(cat("ZstdFrameWriter: ", n, " bytes given, ", left_, " left"));
  left_ -= n;
  ZSTD_inBuffer in{data, n, 0};
  const ZSTD_EndDirective mode = left_ == 0 ? ZSTD_e_end : ZSTD_e_continue;
  for (;;) {
    const std::size_t at = out_.size();
    out_.resize(at + ZSTD_CStreamOutSize());
    ZSTD_outBuffer out{out_.data() + at, ZSTD_CStreamOutSize(), 0};
    const std::size_t r = ZSTD_compressStream2(cctx_, &out, &in, mode);
    if (ZSTD_isError(r)) throw Error(cat("zstd compression failed: ", ZSTD_getErrorName(r)));
    out_.resize(at + out.pos);
    if (mode == ZSTD_e_end ? r == 0 : in.pos == in.size) break;
  }
}

std::vector<std::uint8_t> ZstdFrameWriter::finish() {
  if (left_ != 0)
    throw std::invalid_argument(cat("ZstdFrameWriter: finish() with ", left_, " bytes to come"));
  if (out_.empty()) write(nullptr, 0);  // an empty frame
  return std::move(out_);
}

ZstdFrameReader::ZstdFrameReader(const std::uint8_t* src, std::size_t size, std::string what)
    : src_(src), size_(size), what_(std::move(what)) {
  dctx_ = ZSTD_createDCtx();
  if (!dctx_) throw std::bad_alloc();
}

ZstdFrameReader::~ZstdFrameReader() {
  ZSTD_freeDCtx(dctx_);
}

void ZstdFrameReader::read(std::uint8_t* out_bytes, std::size_t n) {
  ZSTD_outBuffer out{out_bytes, n, 0};
  while (out.pos < out.size) {
    if (ended_) throw FormatError(cat(what_, ": zstd data ends early"));
    ZSTD_inBuffer in{src_, size_, pos_};
    const std::size_t before_in = in.pos, before_out = out.pos;
    const std::size_t r = ZSTD_decompressStream(dctx_, &out, &in);
    if (ZSTD_isError(r))
      throw FormatError(cat(what_, ": zstd data does not decode: ", ZSTD_getErrorName(r)));
    pos_ = in.pos;
    if (r == 0) ended_ = true;
    if (!ended_ && in.pos == before_in && out.pos == before_out)
      throw FormatError(cat(what_, ": zstd data is truncated"));
  }
}

void ZstdFrameReader::finish() {
  if (!ended_) {
    // The frame may end exactly at the last byte read: a call with no room left says so.
    std::uint8_t probe = 0;
    ZSTD_outBuffer out{&probe, 1, 0};
    ZSTD_inBuffer in{src_, size_, pos_};
    const std::size_t r = ZSTD_decompressStream(dctx_, &out, &in);
    if (ZSTD_isError(r))
      throw FormatError(cat(what_, ": zstd data does not decode: ", ZSTD_getErrorName(r)));
    pos_ = in.pos;
    if (out.pos != 0) throw FormatError(cat(what_, ": zstd data holds more bytes than expected"));
    if (r != 0) throw FormatError(cat(what_, ": zstd data is truncated"));
    ended_ = true;
  }
  if (pos_ != size_) throw FormatError(cat(what_, ": trailing bytes after the zstd frame"));
}

void decompress_bytes(const std::uint8_t* src, std::size_t size, std::uint8_t* out,
                      std::size_t out_size, const std::string& what) {
  const std::size_t r = ZSTD_decompress(out, out_size, src, size);
  if (ZSTD_isError(r))
    throw FormatError(cat(what, ": zstd data does not decode: ", ZSTD_getErrorName(r)));
  if (r != out_size)
    throw FormatError(cat(what, ": zstd data decodes to ", r, " bytes, expected ", out_size));
}

int Writer::level_count_for(const std::array<std::int64_t, 3>& dims, int brick_edge) {
  return format::level_count_for(dims, brick_edge);
}

struct Writer::Impl {
  // Work handed to the workers: `count` items, item j made by `make(j, scratch)` (a brick of a
  // slab, or a piece of a slice copy). Fields other than the constants and what `make` writes are
  // guarded by Impl::mutex; what item j writes belongs to whoever makes it until finished[j] is
  // set.
  struct Batch {
    std::function<void(std::int64_t, WorkerScratch&)> make;
    std::int64_t count = 0;
    std::vector<char> finished;
    std::int64_t next = 0;  // next item to hand out
    std::int64_t done = 0;  // items finished
    std::exception_ptr error;
  };

  struct Level {
    std::array<std::int64_t, 3> dims{};
    std::array<std::int64_t, 3> grid{};
    std::int64_t received = 0;
    std::uint64_t index_base = 0;
    // Level 0: per channel, the slab of edge slices being filled (the only full-size buffer):
    // fresh pages that zero slices leave untouched (zero_paged_buffer.h).
    std::vector<ZeroPagedBuffer> slab;
    // Levels >= 1: channel c's slab in the spill store (its id there), and the last two slices
    // received (per channel, two planes), which the next level is reduced from.
    std::vector<int> spill_slab;
    std::vector<std::vector<std::uint8_t>> pair;
    std::vector<std::vector<std::uint8_t>> next_slice;  // per channel: one slice of level + 1
  };

  std::string path;
  WriterOptions opt;
  std::vector<ChannelSpec> stored;
  AtomicFile file;
  int threads = 1;
  VolumeGeometry geometry;
  std::vector<Level> levels;
  std::unique_ptr<detail::SpillStore> spill;  // the coarser levels' slabs
  std::vector<std::uint8_t> band;             // one band of bricks of a coarser level
  std::vector<IndexEntry> entries;
  std::vector<std::vector<std::uint32_t>> entry_labels;
  std::vector<bool> filled;
  // Level-0 slabs encoded elsewhere (provide_level0_slab), by bz, until their slab is flushed.
  struct Provided {
    std::vector<EncodedBrick> bricks;
    const PayloadFile* file = nullptr;  // where bricks with an empty payload have their bytes
  };
  std::map<std::int64_t, Provided> provided;
  bool level1_fed = false;  // append_level1_slice was used (level 0 comes only from provided)
  std::vector<std::uint8_t> zeros = std::vector<std::uint8_t>(kPayloadAlignment, 0);
  std::uint64_t pos = 0;
  std::int64_t slices = 0;
  bool finished = false;

  // Persistent compression workers. A flush hands them a batch and the calling thread makes
  // bricks too, writing each brick as soon as it and every brick before it are made, so the
  // file does not depend on scheduling and few payloads are held at a time.
  std::mutex mutex;
  std::condition_variable work_ready;  // a batch has bricks to hand out, or stop
  std::condition_variable brick_done;  // a brick finished
  Batch* pending = nullptr;            // the batch with bricks not yet handed out
  bool stop = false;
  std::vector<std::thread> workers;
  std::unique_ptr<WorkerScratch> own_scratch;  // the calling thread's

  Impl(std::string p, WriterOptions o) : path(std::move(p)), opt(std::move(o)), file(path) {
    threads = resolve_threads(opt.threads);
    stored = stored_channels_for(opt);
    const int e = opt.brick_edge;
    auto g = make_geometry(opt.dims, opt.spacing_mm, opt.origin_mm, e, int(stored.size()),
                           ReaderLimits{}.max_index_entries);
    if (!g) {
      throw std::invalid_argument(cat(path, ": the bricks exceed the reader's limit of ",
                                      ReaderLimits{}.max_index_entries,
                                      "; use a larger brick_edge"));
    }
    geometry = std::move(*g);
    const int n_levels = int(geometry.levels.size());
    const std::uint64_t base = geometry.index_count;
    spill = std::make_unique<detail::SpillStore>(opt.coarse_levels_memory_bytes, path);
    for (int l = 0; l < n_levels; ++l) {
      const LevelInfo& li = geometry.levels[std::size_t(l)];
      const std::array<std::int64_t, 3>& d = li.dims;
      Level lv;
      lv.dims = d;
      lv.grid = li.bricks;
      lv.index_base = geometry.level_base[std::size_t(l)];
      const std::size_t plane = std::size_t(d[0]) * std::size_t(d[1]);
      const std::size_t planes = std::size_t(std::min<std::int64_t>(e, d[2]));
      for (const auto& s : stored) {
        const std::size_t bytes = channel_type_bytes(s.type);
        if (l == 0) {
          lv.slab.emplace_back(plane * planes * bytes);
        } else {
          lv.spill_slab.push_back(spill->add_slab(int(planes), d[1], std::size_t(d[0]) * bytes, e));
          if (l + 1 < n_levels) lv.pair.emplace_back(2 * plane * bytes);
        }
        if (l + 1 < n_levels) {
          lv.next_slice.emplace_back(std::size_t(ceil_div(d[0], 2)) *
                                     std::size_t(ceil_div(d[1], 2)) * bytes);
        }
      }
      levels.push_back(std::move(lv));
    }
    entries.resize(base);
    entry_labels.resize(base);
    filled.assign(base, false);
    file.write(zeros.data(), zeros.size());  // header placeholder + zero padding up to 4096
    pos = kPayloadAlignment;
    // The calling thread makes bricks too: `threads` in all (parallel_for's convention), so a
    // Writer of one thread compresses on one core.
    workers.reserve(std::size_t(threads - 1));
    try {
      for (int t = 1; t < threads; ++t)
        workers.emplace_back([this] { worker_loop(); });
    } catch (...) {
      stop_workers();
      throw;
    }
  }

  ~Impl() { stop_workers(); }

  void stop_workers() {
    {
      std::lock_guard<std::mutex> lock(mutex);
      stop = true;
    }
    work_ready.notify_all();
    for (auto& t : workers)
      t.join();
    workers.clear();
  }

  // Takes the next brick of the pending batch and makes it; `lock` holds `mutex` on entry and on
  // return, and `pending` is not null.
  void run_one(std::unique_lock<std::mutex>& lock, WorkerScratch& scratch) {
    Batch* b = pending;
    const std::int64_t j = b->next++;
    if (b->next == b->count) pending = nullptr;
    lock.unlock();
    std::exception_ptr error;
    try {
      b->make(j, scratch);
    } catch (...) {
      error = std::current_exception();
    }
    lock.lock();
    if (error && !b->error) b->error = error;
    b->finished[std::size_t(j)] = 1;
    ++b->done;
    brick_done.notify_all();
  }

  void worker_loop() {
    WorkerScratch scratch;
    std::unique_lock<std::mutex> lock(mutex);
    for (;;) {
      work_ready.wait(lock, [&] { return stop || pending; });
      if (stop) return;
      run_one(lock, scratch);
    }
  }

  // Appends one brick's payload and records its index entry (`k`: its index slot).
  void store(std::uint64_t k, IndexEntry en, const std::uint8_t* payload,
             std::vector<std::uint32_t>&& labels) {
    store_with(k, en, std::move(labels), [&] { file.write(payload, en.stored_size); });
  }

  // store() of a payload that lies in `source` at `offset` (en.stored_size bytes), copied from
  // file to file.
  void store_from_file(std::uint64_t k, IndexEntry en, const PayloadFile& source,
                       std::uint64_t offset, std::vector<std::uint32_t>&& labels) {
    store_with(k, en, std::move(labels),
               [&] { file.append_from(source.fd, offset, en.stored_size, source.name); });
  }

  // Records brick k's index entry, its payload (en.stored_size bytes, appended by
  // `write_payload`, then padded to the payload alignment) at the current position.
  template <class WritePayload>
  void store_with(std::uint64_t k, IndexEntry en, std::vector<std::uint32_t>&& labels,
                  WritePayload write_payload) {
    if (en.stored_size) {
      en.offset = pos;
      write_payload();
      const std::uint64_t pad = align_up(en.stored_size, kPayloadAlignment) - en.stored_size;
      if (pad) file.write(zeros.data(), pad);
      pos += en.stored_size + pad;
    }
    entries[k] = en;
    entry_labels[k] = std::move(labels);
    filled[k] = true;
  }

  // Index slot of brick i (slab index order) of slab bz of level L.
  std::uint64_t slot(int L, std::int64_t bz, std::int64_t i) const {
    const Level& lv = levels[std::size_t(L)];
    const std::int64_t per_channel = lv.grid[0] * lv.grid[1];
    const std::uint64_t grid_count = std::uint64_t(per_channel * lv.grid[2]);
    return lv.index_base + std::uint64_t(i / per_channel) * grid_count +
           std::uint64_t(bz * per_channel) + std::uint64_t(i % per_channel);
  }

  // Stops handing out the bricks of `b` and waits for those being made (with `lock` held, which
  // it takes again if needed). Run on every exit from encode_and_write.
  struct BatchDrain {
    Impl& impl;
    Batch& b;
    std::unique_lock<std::mutex>& lock;
    ~BatchDrain() {
      if (!lock.owns_lock()) lock.lock();
      if (impl.pending == &b) impl.pending = nullptr;
      impl.brick_done.wait(lock, [&] { return b.done == b.next; });
    }
  };

  // Makes bricks [first, first + count) of `source` from `blocks` with every thread, writing each
  // in index order as soon as it is made (its payload freed at once).
  void encode_and_write(const BrickSource& source, std::vector<ChannelBlock> blocks,
                        std::int64_t first, std::int64_t count) {
    std::vector<BrickResult> results(static_cast<std::size_t>(count));
    const std::int64_t per_channel = source.gx * source.gy;
    Batch b;
    b.make = [&](std::int64_t j, WorkerScratch& scratch) {
      const std::int64_t i = first + j;
      encode_brick(opt, stored, path, source, blocks[std::size_t(i / per_channel)], i, scratch,
                   results[std::size_t(j)]);
    };
    b.count = count;
    b.finished.assign(std::size_t(count), 0);
    if (!own_scratch) own_scratch = std::make_unique<WorkerScratch>();
    std::unique_lock<std::mutex> lock(mutex);
    pending = &b;
    work_ready.notify_all();
    // However this function is left (a brick failed, or writing a finished brick threw, e.g.
    // ENOSPC), `b` lives on this stack: hand out nothing more of it and wait until no worker
    // still makes one of its bricks, before it goes out of scope.
    BatchDrain drain{*this, b, lock};
    for (std::int64_t j = 0; j < count; ++j) {
      while (!b.finished[std::size_t(j)] && !b.error) {
        if (pending == &b) {
          run_one(lock, *own_scratch);
        } else {
          brick_done.wait(lock);
        }
      }
      if (b.error) std::rethrow_exception(b.error);  // `drain` waits for the bricks in flight
      lock.unlock();
      BrickResult& r = results[std::size_t(j)];
      store(slot(source.level, source.bz, first + j), r.entry, r.payload.data(),
            std::move(r.labels));
      std::vector<std::uint8_t>().swap(r.payload);
      lock.lock();
    }
  }

  // Runs items [0, count) of `make` on every thread (the calling thread included) and returns
  // when all are done; the first error is rethrown after the items in flight have finished.
  void run_all(std::int64_t count, const std::function<void(std::int64_t, WorkerScratch&)>& make) {
    if (count <= 0) return;
    if (!own_scratch) own_scratch = std::make_unique<WorkerScratch>();
    if (workers.empty() || count == 1) {
      for (std::int64_t j = 0; j < count; ++j)
        make(j, *own_scratch);
      return;
    }
    Batch b;
    b.make = make;
    b.count = count;
    b.finished.assign(std::size_t(count), 0);
    std::unique_lock<std::mutex> lock(mutex);
    pending = &b;
    work_ready.notify_all();
    BatchDrain drain{*this, b, lock};
    while (b.done < count && !b.error) {
      if (pending == &b) {
        run_one(lock, *own_scratch);
      } else {
        brick_done.wait(lock);
      }
    }
    if (b.error) std::rethrow_exception(b.error);
  }

  // Copies `n` bytes from `src` to `dst` on every thread, in pieces of about kCopyPiece bytes:
  // filling the level-0 slab is most of a slab's work outside its flush (and, the first time,
  // the page faults of a fresh slab), so the workers, idle until the flush, share it.
  // The pieces are aligned on multiples of kCopyPiece within the slab (a multiple of the page
  // size), so no two share a page (ZeroPagedBuffer's condition for writing at once).
  static constexpr std::size_t kCopyPiece = std::size_t(4) << 20;
  template <class Write>
  void write_parallel(std::size_t at, std::size_t n, std::size_t piece, Write write) {
    const std::size_t base = at / piece * piece, end = at + n;
    const std::int64_t pieces = std::int64_t((end - base + piece - 1) / piece);
    run_all(pieces, [&](std::int64_t k, WorkerScratch&) {
      const std::size_t from = std::max(at, base + std::size_t(k) * piece);
      const std::size_t to = std::min(end, base + std::size_t(k + 1) * piece);
      write(from, to - from);
    });
  }
  void copy_parallel(ZeroPagedBuffer& dst, std::size_t at, const std::uint8_t* src, std::size_t n) {
    write_parallel(at, n, kCopyPiece, [&](std::size_t from, std::size_t count) {
      dst.write(from, src + (from - at), count);
    });
  }
  // uint16 label IDs (checked to fit) narrowed to uint8 into the slab: reads 2, writes 1 byte
  // per ID, so a quarter of kCopyPiece per piece.
  void narrow_parallel(ZeroPagedBuffer& dst, std::size_t at, const std::uint16_t* src,
                       std::size_t n) {
    static_assert((kCopyPiece / 4) % 65536 == 0, "pieces must be whole pages");
    write_parallel(at, n, kCopyPiece / 4, [&](std::size_t from, std::size_t count) {
      dst.write_narrowed(from, src + (from - at), count);
    });
  }

  // Encodes and writes slab `bz` of level L (its first nzv slices valid).
  void flush(int L, std::int64_t bz, int nzv) {
    Level& lv = levels[std::size_t(L)];
    const std::int64_t gx = lv.grid[0], gy = lv.grid[1];
    const std::int64_t dx = lv.dims[0], dy = lv.dims[1];
    const std::int64_t per_channel = gx * gy;
    const std::int64_t items = per_channel * std::int64_t(stored.size());
    const BrickSource source{L, bz, nzv, gx, gy, dx, dy};
    if (L == 0) {
      auto given = provided.find(bz);
      if (given != provided.end()) {
        // Encoded elsewhere (a shard of a sharded pack): stored as handed over, not re-encoded.
        const PayloadFile* file = given->second.file;
        for (std::int64_t i = 0; i < items; ++i) {
          EncodedBrick& eb = given->second.bricks[std::size_t(i)];
          IndexEntry en{};
          en.bx = std::uint32_t((i % per_channel) % gx);
          en.by = std::uint32_t((i % per_channel) / gx);
          en.bz = std::uint32_t(bz);
          en.level = 0;
          en.channel = std::uint8_t(i / per_channel);
          en.codec = std::uint8_t(eb.codec);
          std::memcpy(en.min, eb.min.data(), 8);
          std::memcpy(en.max, eb.max.data(), 8);
          en.checksum = eb.checksum;
          if (file && eb.payload.empty() && eb.file_bytes > 0) {
            en.stored_size = eb.file_bytes;
            store_from_file(slot(0, bz, i), en, *file, eb.file_offset, std::move(eb.labels));
          } else {
            en.stored_size = eb.payload.size();
            store(slot(0, bz, i), en, eb.payload.data(), std::move(eb.labels));
          }
          std::vector<std::uint8_t>().swap(eb.payload);
        }
        provided.erase(given);
        return;
      }
      if (level1_fed) {
        throw std::invalid_argument(cat(path, ": level-0 slab ", bz,
                                        " was not provided (provide_level0_slab) before its "
                                        "level-1 slices were appended"));
      }
      std::vector<ChannelBlock> blocks;
      for (const auto& s : lv.slab)
        blocks.push_back({s.data(), 0, dy, &s});
      encode_and_write(source, std::move(blocks), 0, items);
      return;
    }
    // A coarser level: its slab is in the spill store; one band of bricks (one brick row along
    // y of one channel) is read back at a time.
    for (std::size_t c = 0; c < stored.size(); ++c) {
      const std::size_t bytes = channel_type_bytes(stored[c].type);
      for (std::int64_t by = 0; by < gy; ++by) {
        const std::int64_t y0 = by * opt.brick_edge;
        const std::int64_t rows = std::min<std::int64_t>(opt.brick_edge, dy - y0);
        const std::size_t run = std::size_t(rows) * std::size_t(dx) * bytes;
        if (band.size() < run * std::size_t(nzv)) band.resize(run * std::size_t(nzv));
        for (int z = 0; z < nzv; ++z)
          spill->get_band(lv.spill_slab[c], z, by, band.data() + std::size_t(z) * run);
        std::vector<ChannelBlock> blocks(stored.size());
        blocks[c] = {band.data(), y0, rows};
        encode_and_write(source, std::move(blocks), std::int64_t(c) * per_channel + by * gx, gx);
      }
    }
  }

  // Slice z of level L (for level 0, `slices_in[c]` may already point into the slab: then it is
  // not copied). Reduces the next level's slice from every pair, and writes a slab once full:
  // the coarser levels' slabs that fill with it first (coarsest first), then this one.
  void push(int L, const std::vector<const std::uint8_t*>& slices_in) {
    Level& lv = levels[std::size_t(L)];
    const std::int64_t e = opt.brick_edge;
    const std::int64_t z = lv.received++;
    const std::int64_t zs = z % e;
    const std::size_t plane = std::size_t(lv.dims[0]) * std::size_t(lv.dims[1]);
    const bool has_next = L + 1 < int(levels.size());
    if (L == 0) {
      for (std::size_t c = 0; c < stored.size(); ++c) {
        const std::size_t bytes = channel_type_bytes(stored[c].type);
        const std::size_t at = std::size_t(zs) * plane * bytes;
        if (slices_in[c] != lv.slab[c].data() + at)
          copy_parallel(lv.slab[c], at, slices_in[c], plane * bytes);
      }
    } else {
      // Into the spill store band by band (each compressed on its own), on every thread.
      const std::int64_t bands = spill->band_count(lv.spill_slab[0]);
      run_all(bands * std::int64_t(stored.size()), [&](std::int64_t k, WorkerScratch& scratch) {
        const std::size_t c = std::size_t(k / bands);
        const std::int64_t band = k % bands;
        const std::size_t row = std::size_t(lv.dims[0]) * channel_type_bytes(stored[c].type);
        spill->put_band(lv.spill_slab[c], int(zs), band, slices_in[c] + std::size_t(band * e) * row,
                        scratch.cctx, scratch.out);
      });
      if (has_next) {
        for (std::size_t c = 0; c < stored.size(); ++c) {
          const std::size_t bytes = channel_type_bytes(stored[c].type);
          std::memcpy(lv.pair[c].data() + std::size_t(z % 2) * plane * bytes, slices_in[c],
                      plane * bytes);
        }
      }
    }
    const bool last = z == lv.dims[2] - 1;
    if (has_next && (z % 2 == 1 || last)) {
      const std::int64_t z0 = zs & ~std::int64_t(1);
      std::vector<const std::uint8_t*> next(stored.size());
      for (std::size_t c = 0; c < stored.size(); ++c) {
        const std::size_t bytes = channel_type_bytes(stored[c].type);
        const std::uint8_t* src =
            L == 0 ? lv.slab[c].data() + std::size_t(z0) * plane * bytes : lv.pair[c].data();
        downsample_slice(stored[c].type, src, z % 2 == 1 ? 2 : 1, lv.dims[0], lv.dims[1],
                         lv.next_slice[c].data(), threads, L == 0 ? &lv.slab[c] : nullptr);
        next[c] = lv.next_slice[c].data();
      }
      push(L + 1, next);
    }
    if (zs == e - 1 || last) flush(L, z / e, int(zs + 1));
  }

  // Where slice `received` of level 0, channel c, goes in the slab (a byte offset in it).
  std::size_t level0_offset(std::size_t c) const {
    const Level& lv = levels[0];
    const std::size_t plane = std::size_t(lv.dims[0]) * std::size_t(lv.dims[1]);
    const std::int64_t zs = lv.received % opt.brick_edge;
    return std::size_t(zs) * plane * channel_type_bytes(stored[c].type);
  }

  // Level-1 slice z1 given directly (append_level1_slice): level 0 advances by the (one or two)
  // slices it was reduced from, and the level-0 slab they complete is written from its provided
  // bricks after the coarser levels, in the order append_slice would have written them.
  void push_level1(const std::vector<const std::uint8_t*>& slices_in) {
    Level& l0 = levels[0];
    const std::int64_t e = opt.brick_edge;
    const std::int64_t z0 = l0.received;
    const std::int64_t n0 = std::min<std::int64_t>(2, l0.dims[2] - z0);
    push(1, slices_in);
    l0.received += n0;
    slices += n0;
    const std::int64_t z = l0.received - 1;
    if (z % e == e - 1 || z == l0.dims[2] - 1) flush(0, z / e, int(z % e + 1));
  }

  void finish() {
    stop_workers();
    const std::uint64_t payload_end = pos;
    std::vector<std::uint32_t> label_ids;
    for (std::size_t k = 0; k < entries.size(); ++k) {
      if (!filled[k]) throw Error(cat(path, ": internal error: brick ", k, " was never written"));
      if (!entry_labels[k].empty()) {
        entries[k].label_first = std::uint32_t(label_ids.size());
        entries[k].label_count = std::uint32_t(entry_labels[k].size());
        label_ids.insert(label_ids.end(), entry_labels[k].begin(), entry_labels[k].end());
      }
    }
    std::string meta = metadata().dump();
    detail::FileHeader h{};
    std::memcpy(h.magic, detail::kMagic, 8);
    h.version_major = kFormatMajor;
    h.version_minor = kFormatMinor;
    h.header_size = detail::kHeaderSize;
    h.payload_offset = kPayloadAlignment;
    h.payload_end = payload_end;
    h.metadata_offset = payload_end;
    h.metadata_size = meta.size();
    h.index_offset = align_up(payload_end + meta.size(), 8);
    h.index_count = entries.size();
    h.labels_offset = h.index_offset + entries.size() * sizeof(IndexEntry);
    h.labels_count = label_ids.size();
    h.file_size = h.labels_offset + label_ids.size() * 4;
    h.index_entry_size = detail::kIndexEntrySize;
    h.brick_edge = std::uint32_t(opt.brick_edge);
    h.level_count = std::uint32_t(levels.size());
    h.channel_count = std::uint32_t(stored.size());

    XXH64_state_t* state = XXH64_createState();
    if (!state) throw std::bad_alloc();
    XXH64_reset(state, 0);
    XXH64_update(state, &h, detail::kChecksumFieldOffset);
    XXH64_update(state, meta.data(), meta.size());
    XXH64_update(state, zeros.data(), h.index_offset - (payload_end + meta.size()));
    XXH64_update(state, entries.data(), entries.size() * sizeof(IndexEntry));
    XXH64_update(state, label_ids.data(), label_ids.size() * 4);
    h.table_checksum = XXH64_digest(state);
    XXH64_freeState(state);

    file.write(meta);
    std::uint64_t pad = h.index_offset - (payload_end + meta.size());
    if (pad) file.write(zeros.data(), pad);
    file.write(entries.data(), entries.size() * sizeof(IndexEntry));
    file.write(label_ids.data(), label_ids.size() * 4);
    if (file.size() != h.file_size) {
      throw Error(
          cat(path, ": internal error: wrote ", file.size(), " bytes, expected ", h.file_size));
    }
    file.pwrite(&h, sizeof(h), 0);
    file.commit();
  }

  nlohmann::json metadata() const {
    VolumeMetadata meta;
    meta.dims = opt.dims;
    meta.spacing_mm = opt.spacing_mm;
    meta.origin_mm = opt.origin_mm;
    meta.brick_edge = opt.brick_edge;
    meta.channels = stored;
    meta.label_table = opt.label_table;
    meta.extra = opt.extra_metadata;
    return metadata_json(meta, geometry);
  }
};

Writer::Writer(std::string path, WriterOptions options) {
  validate(options);
  impl_ = std::make_unique<Impl>(std::move(path), std::move(options));
}
Writer::~Writer() = default;
Writer::Writer(Writer&&) noexcept = default;
Writer& Writer::operator=(Writer&&) noexcept = default;

std::int64_t Writer::slices_written() const {
  return impl_->slices;
}
const std::vector<ChannelSpec>& Writer::stored_channels() const {
  return impl_->stored;
}

void Writer::append_slice(const std::vector<const void*>& channel_slices) {
  Impl& m = *impl_;
  if (m.finished) throw std::invalid_argument(cat(m.path, ": append_slice after finish()"));
  if (channel_slices.size() != m.stored.size()) {
    throw std::invalid_argument(cat(m.path, ": append_slice got ", channel_slices.size(),
                                    " channel pointers, expected ", m.stored.size()));
  }
  if (m.slices >= m.opt.dims[2]) {
    throw std::invalid_argument(
        cat(m.path, ": append_slice: already got all ", m.opt.dims[2], " slices"));
  }
  if (m.level1_fed)
    throw std::invalid_argument(cat(m.path, ": append_slice after append_level1_slice"));
  const std::size_t plane = std::size_t(m.opt.dims[0]) * std::size_t(m.opt.dims[1]);
  std::vector<const std::uint8_t*> in(m.stored.size());
  for (std::size_t c = 0; c < m.stored.size(); ++c) {
    if (!channel_slices[c]) {
      throw std::invalid_argument(
          cat(m.path, ": append_slice: null pointer for channel \"", m.stored[c].name, "\""));
    }
    in[c] = static_cast<const std::uint8_t*>(channel_slices[c]);
    if (is_label_type(m.stored[c].type) && m.stored[c].type == ChannelType::kUint8) {
      // Narrowed straight into the level-0 slab; checked first, so a bad slice leaves the
      // slab as it was.
      const std::size_t at = m.level0_offset(c);
      const auto* src = static_cast<const std::uint16_t*>(channel_slices[c]);
      check_labels_fit_uint8(src, plane, m.opt.dims[0], m.path, m.slices, m.stored[c].name);
      m.narrow_parallel(m.levels[0].slab[c], at, src, plane);
      in[c] = m.levels[0].slab[c].data() + at;
    }
  }
  m.push(0, in);
  ++m.slices;
}

void Writer::append_level1_slice(const std::vector<const void*>& channel_slices) {
  Impl& m = *impl_;
  if (m.finished) throw std::invalid_argument(cat(m.path, ": append_level1_slice after finish()"));
  if (m.levels.size() < 2) {
    throw std::invalid_argument(
        cat(m.path, ": append_level1_slice: the volume has no level 1 (it fits one brick)"));
  }
  if (m.slices > 0 && !m.level1_fed)
    throw std::invalid_argument(cat(m.path, ": append_level1_slice after append_slice"));
  if (channel_slices.size() != m.stored.size()) {
    throw std::invalid_argument(cat(m.path, ": append_level1_slice got ", channel_slices.size(),
                                    " channel pointers, expected ", m.stored.size()));
  }
  if (m.slices >= m.opt.dims[2]) {
    throw std::invalid_argument(
        cat(m.path, ": append_level1_slice: already got all ", m.opt.dims[2], " slices"));
  }
  const std::int64_t bz = m.slices / m.opt.brick_edge;
  if (!m.provided.count(bz)) {
    throw std::invalid_argument(cat(m.path, ": append_level1_slice: level-0 slab ", bz,
                                    " must be provided (provide_level0_slab) first"));
  }
  std::vector<const std::uint8_t*> in(m.stored.size());
  for (std::size_t c = 0; c < m.stored.size(); ++c) {
    if (!channel_slices[c]) {
      throw std::invalid_argument(cat(m.path, ": append_level1_slice: null pointer for channel \"",
                                      m.stored[c].name, "\""));
    }
    in[c] = static_cast<const std::uint8_t*>(channel_slices[c]);
  }
  m.level1_fed = true;
  m.push_level1(in);
}

void Writer::provide_level0_slab(std::int64_t bz, std::vector<EncodedBrick> bricks,
                                 const PayloadFile* file) {
  Impl& m = *impl_;
  const std::int64_t e = m.opt.brick_edge;
  if (bz < 0 || bz >= level0_slab_count(m.opt)) {
    throw std::invalid_argument(cat(m.path, ": provide_level0_slab: slab ", bz, " is outside [0, ",
                                    level0_slab_count(m.opt), ")"));
  }
  const std::int64_t last = std::min((bz + 1) * e, m.opt.dims[2]) - 1;
  if (m.slices > last || m.provided.count(bz)) {
    throw std::invalid_argument(
        cat(m.path, ": provide_level0_slab: slab ", bz, " was already flushed or provided"));
  }
  const Impl::Level& lv = m.levels[0];
  const std::int64_t items = lv.grid[0] * lv.grid[1] * std::int64_t(m.stored.size());
  if (std::int64_t(bricks.size()) != items) {
    throw std::invalid_argument(cat(m.path, ": provide_level0_slab: slab ", bz, " has ",
                                    bricks.size(), " bricks, expected ", items));
  }
  m.provided.emplace(bz, Impl::Provided{std::move(bricks), file});
}

void Writer::finish() {
  Impl& m = *impl_;
  if (m.finished) throw std::invalid_argument(cat(m.path, ": finish() called twice"));
  if (m.slices == 0 && m.levels.size() == 1 && m.provided.count(0)) {
    // A single-level volume given as its one encoded slab (no level 1 to append).
    m.flush(0, 0, int(m.opt.dims[2]));
    m.slices = m.opt.dims[2];
  }
  if (m.slices != m.opt.dims[2]) {
    throw std::invalid_argument(
        cat(m.path, ": finish() after ", m.slices, " of ", m.opt.dims[2], " slices"));
  }
  m.finish();
  m.finished = true;
}

void write_volume(const std::string& path, const WriterOptions& options,
                  const std::vector<const void*>& channel_volumes) {
  Writer writer(path, options);
  const auto& stored = writer.stored_channels();
  if (channel_volumes.size() != stored.size()) {
    throw std::invalid_argument(cat(path, ": write_volume got ", channel_volumes.size(),
                                    " channel volumes, expected ", stored.size()));
  }
  const std::size_t plane = std::size_t(options.dims[0]) * std::size_t(options.dims[1]);
  std::vector<const void*> slice(stored.size());
  for (std::int64_t z = 0; z < options.dims[2]; ++z) {
    for (std::size_t c = 0; c < stored.size(); ++c) {
      std::size_t bytes = is_label_type(stored[c].type) ? 2 : channel_type_bytes(stored[c].type);
      slice[c] =
          static_cast<const std::uint8_t*>(channel_volumes[c]) + std::size_t(z) * plane * bytes;
    }
    writer.append_slice(slice);
  }
  writer.finish();
}

}  // namespace vispack::format

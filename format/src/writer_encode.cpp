// The brick encoder and the payload codecs of the format writer: one brick gathered, its stats
// and its stored bytes (SPEC.md "Codecs"); zstd frames; the decoding of an encoded brick.
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

#include "writer_encode.h"

namespace vispack::format {
namespace detail {
namespace {

constexpr std::int64_t kMaxDim = (std::int64_t(1) << 31) - 1;

bool is_power_of_two(int v) {
  return v > 0 && (v & (v - 1)) == 0;
}

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

}  // namespace

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

}  // namespace detail

using namespace detail;

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

}  // namespace vispack::format

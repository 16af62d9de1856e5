// Level-0 slabs encoded apart from a Writer (a shard of a sharded pack), and the stored channel
// types: writer.h "Sharded writing".
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

using namespace detail;

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

}  // namespace vispack::format

// Writer::Impl: the pyramid levels, their slabs and how a slice moves through them (writer_impl.h).
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

#include "writer_impl.h"

namespace vispack::format {

using namespace detail;

Writer::Impl::Impl(std::string p, WriterOptions o)
    : path(std::move(p)), opt(std::move(o)), file(path) {
  threads = resolve_threads(opt.threads);
  stored = stored_channels_for(opt);
  const int e = opt.brick_edge;
  auto g = make_geometry(opt.dims, opt.spacing_mm, opt.origin_mm, e, int(stored.size()),
                         ReaderLimits{}.max_index_entries);
  if (!g) {
    throw std::invalid_argument(cat(path, ": the bricks exceed the reader's limit of ",
                                    ReaderLimits{}.max_index_entries, "; use a larger brick_edge"));
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
        lv.next_slice.emplace_back(std::size_t(ceil_div(d[0], 2)) * std::size_t(ceil_div(d[1], 2)) *
                                   bytes);
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

void Writer::Impl::flush(int L, std::int64_t bz, int nzv) {
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

void Writer::Impl::push(int L, const std::vector<const std::uint8_t*>& slices_in) {
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

std::size_t Writer::Impl::level0_offset(std::size_t c) const {
  const Level& lv = levels[0];
  const std::size_t plane = std::size_t(lv.dims[0]) * std::size_t(lv.dims[1]);
  const std::int64_t zs = lv.received % opt.brick_edge;
  return std::size_t(zs) * plane * channel_type_bytes(stored[c].type);
}

void Writer::Impl::push_level1(const std::vector<const std::uint8_t*>& slices_in) {
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

}  // namespace vispack::format

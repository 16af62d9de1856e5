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

int Writer::level_count_for(const std::array<std::int64_t, 3>& dims, int brick_edge) {
  return format::level_count_for(dims, brick_edge);
}

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

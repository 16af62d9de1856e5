// Writer::Impl: payload I/O, each brick's stored bytes appended and its index slot (writer_impl.h).
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

void Writer::Impl::store(std::uint64_t k, IndexEntry en, const std::uint8_t* payload,
                         std::vector<std::uint32_t>&& labels) {
  store_with(k, en, std::move(labels), [&] { file.write(payload, en.stored_size); });
}

void Writer::Impl::store_from_file(std::uint64_t k, IndexEntry en, const PayloadFile& source,
                                   std::uint64_t offset, std::vector<std::uint32_t>&& labels) {
  store_with(k, en, std::move(labels),
             [&] { file.append_from(source.fd, offset, en.stored_size, source.name); });
}

std::uint64_t Writer::Impl::slot(int L, std::int64_t bz, std::int64_t i) const {
  const Level& lv = levels[std::size_t(L)];
  const std::int64_t per_channel = lv.grid[0] * lv.grid[1];
  const std::uint64_t grid_count = std::uint64_t(per_channel * lv.grid[2]);
  return lv.index_base + std::uint64_t(i / per_channel) * grid_count +
         std::uint64_t(bz * per_channel) + std::uint64_t(i % per_channel);
}

}  // namespace vispack::format

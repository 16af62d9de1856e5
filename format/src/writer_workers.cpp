// Writer::Impl: the compression workers and the batches they share (writer_impl.h).
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

void Writer::Impl::stop_workers() {
  {
    std::lock_guard<std::mutex> lock(mutex);
    stop = true;
  }
  work_ready.notify_all();
  for (auto& t : workers)
    t.join();
  workers.clear();
}

void Writer::Impl::run_one(std::unique_lock<std::mutex>& lock, WorkerScratch& scratch) {
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

void Writer::Impl::worker_loop() {
  WorkerScratch scratch;
  std::unique_lock<std::mutex> lock(mutex);
  for (;;) {
    work_ready.wait(lock, [&] { return stop || pending; });
    if (stop) return;
    run_one(lock, scratch);
  }
}

void Writer::Impl::encode_and_write(const BrickSource& source, std::vector<ChannelBlock> blocks,
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
    store(slot(source.level, source.bz, first + j), r.entry, r.payload.data(), std::move(r.labels));
    std::vector<std::uint8_t>().swap(r.payload);
    lock.lock();
  }
}

void Writer::Impl::run_all(std::int64_t count,
                           const std::function<void(std::int64_t, WorkerScratch&)>& make) {
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

void Writer::Impl::copy_parallel(ZeroPagedBuffer& dst, std::size_t at, const std::uint8_t* src,
                                 std::size_t n) {
  write_parallel(at, n, kCopyPiece, [&](std::size_t from, std::size_t count) {
    dst.write(from, src + (from - at), count);
  });
}

void Writer::Impl::narrow_parallel(ZeroPagedBuffer& dst, std::size_t at, const std::uint16_t* src,
                                   std::size_t n) {
  static_assert((kCopyPiece / 4) % 65536 == 0, "pieces must be whole pages");
  write_parallel(at, n, kCopyPiece / 4, [&](std::size_t from, std::size_t count) {
    dst.write_narrowed(from, src + (from - at), count);
  });
}

}  // namespace vispack::format

// Writer::Impl, the state of one Writer (private to the format writer): declared here, defined
// by concern: the levels and their slabs (writer_levels.cpp), the compression workers
// (writer_workers.cpp), payload I/O (writer_payload.cpp), the brick index, metadata and header
// (writer_index.cpp). Not thread-safe: one Writer is used by one thread; its workers share the
// fields guarded by `mutex`.
#pragma once

#include <array>
#include <condition_variable>
#include <cstdint>
#include <exception>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "spill_store.h"
#include "vispack/common/atomic_file.h"
#include "vispack/format/geometry.h"
#include "writer_encode.h"

namespace vispack::format {

using detail::align_up;
using detail::BrickResult;
using detail::BrickSource;
using detail::ChannelBlock;
using detail::IndexEntry;
using detail::WorkerScratch;

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

  Impl(std::string p, WriterOptions o);

  ~Impl() { stop_workers(); }

  void stop_workers();

  // Takes the next brick of the pending batch and makes it; `lock` holds `mutex` on entry and on
  // return, and `pending` is not null.
  void run_one(std::unique_lock<std::mutex>& lock, WorkerScratch& scratch);

  void worker_loop();

  // Appends one brick's payload and records its index entry (`k`: its index slot).
  void store(std::uint64_t k, IndexEntry en, const std::uint8_t* payload,
             std::vector<std::uint32_t>&& labels);

  // store() of a payload that lies in `source` at `offset` (en.stored_size bytes), copied from
  // file to file.
  void store_from_file(std::uint64_t k, IndexEntry en, const PayloadFile& source,
                       std::uint64_t offset, std::vector<std::uint32_t>&& labels);

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
  std::uint64_t slot(int L, std::int64_t bz, std::int64_t i) const;

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
                        std::int64_t first, std::int64_t count);

  // Runs items [0, count) of `make` on every thread (the calling thread included) and returns
  // when all are done; the first error is rethrown after the items in flight have finished.
  void run_all(std::int64_t count, const std::function<void(std::int64_t, WorkerScratch&)>& make);

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
  void copy_parallel(ZeroPagedBuffer& dst, std::size_t at, const std::uint8_t* src, std::size_t n);
  // uint16 label IDs (checked to fit) narrowed to uint8 into the slab: reads 2, writes 1 byte
  // per ID, so a quarter of kCopyPiece per piece.
  void narrow_parallel(ZeroPagedBuffer& dst, std::size_t at, const std::uint16_t* src,
                       std::size_t n);

  // Encodes and writes slab `bz` of level L (its first nzv slices valid).
  void flush(int L, std::int64_t bz, int nzv);

  // Slice z of level L (for level 0, `slices_in[c]` may already point into the slab: then it is
  // not copied). Reduces the next level's slice from every pair, and writes a slab once full:
  // the coarser levels' slabs that fill with it first (coarsest first), then this one.
  void push(int L, const std::vector<const std::uint8_t*>& slices_in);

  // Where slice `received` of level 0, channel c, goes in the slab (a byte offset in it).
  std::size_t level0_offset(std::size_t c) const;

  // Level-1 slice z1 given directly (append_level1_slice): level 0 advances by the (one or two)
  // slices it was reduced from, and the level-0 slab they complete is written from its provided
  // bricks after the coarser levels, in the order append_slice would have written them.
  void push_level1(const std::vector<const std::uint8_t*>& slices_in);

  void finish();

  nlohmann::json metadata() const;
};

}  // namespace vispack::format

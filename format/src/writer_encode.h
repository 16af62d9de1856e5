// The format writer's private parts shared by its files (not installed): the brick encoder
// (writer_encode.cpp) and what it works with. The Writer's own state is writer_impl.h.
#pragma once

#include <zstd.h>

#include <cstdint>
#include <string>
#include <vector>

#include "int_math.h"
#include "layout.h"
#include "vispack/common/zero_paged_buffer.h"
#include "vispack/format/writer.h"

namespace vispack::format::detail {

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

// Throws std::invalid_argument naming the option at fault unless `o` is a volume the format can
// hold.
void validate(const WriterOptions& o);

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
                  std::int64_t i, WorkerScratch& scratch, BrickResult& r);

// Throws InputError unless every ID of a uint16 label slice fits uint8 (the stored type); `what`,
// `slice` and `channel` name the slice in the error.
void check_labels_fit_uint8(const std::uint16_t* src, std::size_t plane, std::int64_t nx,
                            const std::string& what, std::int64_t slice,
                            const std::string& channel);

// Narrows a uint16 label slice to uint8, refusing IDs above 255 (checked first: `dst` is untouched
// on error).
void narrow_labels(const std::uint16_t* src, std::size_t plane, std::int64_t nx, std::uint8_t* dst,
                   const std::string& what, std::int64_t slice, const std::string& channel);

}  // namespace vispack::format::detail

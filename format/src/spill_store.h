// Internal to the format writer: the partly filled slabs of the coarser pyramid levels
// (writer.h, "Memory"), kept as zstd-compressed strips. A slab is `planes` planes of `rows` rows
// of `row_bytes` bytes; each plane is stored in bands of `band_rows` rows (a band is what one
// brick row along y needs), each band compressed on its own (zstd level 1, or raw when that is
// not smaller), so a band of bricks is read back without touching the rest of the plane.
// Compressed strips stay in memory while the memory they hold stays within `memory_limit`;
// further strips go to an unlinked temporary file beside the output (each strip in a fixed slot
// of its raw size), so their bytes live in the page cache, not in the resident set.
// Why compressed: outside the body a coarser level is mostly uniform, so its strips are a small
// fraction of their raw size; held raw (a third of a level-0 brick row) they were written to and
// read back from the file, and on a machine whose fresh pages are expensive (a VM returning free
// memory to its host) those page-cache copies cost about as much as the slab's compression.
// Ownership: RAII; the file has no name once created (unlinked at once), so nothing is left
// behind, whatever happens. Thread-safety: put_band may be called from several threads at once
// for different strips (each with its own ZSTD_CCtx); get_band and add_slab from one thread, not
// concurrently with put_band.
#pragma once

#include <zstd.h>

#include <cstddef>
#include <cstdint>
#include <mutex>
#include <string>
#include <vector>

namespace vispack::format::detail {

class SpillStore {
 public:
  // `near_path`: where the temporary file goes (created on first need; IoError naming it if it
  // cannot be), and the name errors give.
  SpillStore(std::uint64_t memory_limit, const std::string& near_path);
  ~SpillStore();
  SpillStore(const SpillStore&) = delete;
  SpillStore& operator=(const SpillStore&) = delete;

  // Registers a slab; returns its id (0, 1, ... in call order).
  int add_slab(int planes, std::int64_t rows, std::size_t row_bytes, std::int64_t band_rows);
  std::int64_t band_count(int slab) const;

  // Stores band `band` of plane `z` of `slab`: min(band_rows, rows - band * band_rows) rows at
  // `data`, compressed with `cctx` into `work` (the calling thread's: resized as needed);
  // replaces what that strip held. Throws IoError (file write), Error (zstd).
  void put_band(int slab, int z, std::int64_t band, const std::uint8_t* data, ZSTD_CCtx* cctx,
                std::vector<std::uint8_t>& work);
  // Copies that band back to `out`. Throws IoError, FormatError (a strip that does not decode:
  // an internal error), std::logic_error (a strip never stored).
  void get_band(int slab, int z, std::int64_t band, std::uint8_t* out);

 private:
  struct Strip {
    bool stored = false;
    bool raw = false;      // bytes are the raw band (zstd did not make it smaller)
    bool in_file = false;  // bytes are in the file slot, not in `bytes`
    std::size_t size = 0;  // stored bytes
    std::vector<std::uint8_t> bytes;
  };
  struct Slab {
    int planes = 0;
    std::int64_t rows = 0, band_rows = 0, bands = 0;
    std::size_t row_bytes = 0;
    std::uint64_t file_base = 0;  // where its slots start in the file
    std::vector<Strip> strips;    // planes * bands
  };
  std::size_t band_bytes(const Slab& s, std::int64_t band) const;
  std::uint64_t slot_offset(const Slab& s, int z, std::int64_t band) const;
  void open_file();  // with mutex_ held

  std::string near_path_;
  std::string what_;  // names the store in errors
  std::uint64_t memory_limit_ = 0;
  std::uint64_t memory_used_ = 0;  // capacity of the strips' memory buffers
  std::uint64_t file_bytes_ = 0;   // slots reserved so far
  std::vector<Slab> slabs_;
  int fd_ = -1;
  ZSTD_DCtx* dctx_ = nullptr;
  std::mutex mutex_;
  std::vector<std::uint8_t> scratch_;  // get_band's compressed bytes read from the file
};

}  // namespace vispack::format::detail

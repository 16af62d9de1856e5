#include "spill_store.h"

#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <stdexcept>

#include "vispack/common/error.h"

namespace vispack::format::detail {
namespace {

// zstd level of the strips: they are read back once, so speed matters more than size.
constexpr int kStripLevel = 1;

void pwrite_all(int fd, const std::uint8_t* p, std::size_t n, std::uint64_t offset,
                const std::string& what) {
  while (n > 0) {
    const ssize_t w = ::pwrite(fd, p, n, off_t(offset));
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) throw IoError(cat(what, ": write failed: ", std::strerror(errno)));
    p += w;
    n -= std::size_t(w);
    offset += std::uint64_t(w);
  }
}

void pread_all(int fd, std::uint8_t* p, std::size_t n, std::uint64_t offset,
               const std::string& what) {
  while (n > 0) {
    const ssize_t r = ::pread(fd, p, n, off_t(offset));
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) throw IoError(cat(what, ": read failed: ", r < 0 ? std::strerror(errno) : "EOF"));
    p += r;
    n -= std::size_t(r);
    offset += std::uint64_t(r);
  }
}

}  // namespace

SpillStore::SpillStore(std::uint64_t memory_limit, const std::string& near_path)
    : near_path_(near_path),
      what_(near_path + " (scratch of the coarser levels)"),
      memory_limit_(memory_limit) {
  dctx_ = ZSTD_createDCtx();
  if (!dctx_) throw std::bad_alloc();
}

SpillStore::~SpillStore() {
  if (fd_ >= 0) ::close(fd_);
  ZSTD_freeDCtx(dctx_);
}

int SpillStore::add_slab(int planes, std::int64_t rows, std::size_t row_bytes,
                         std::int64_t band_rows) {
  Slab s;
  s.planes = planes;
  s.rows = rows;
  s.row_bytes = row_bytes;
  s.band_rows = band_rows;
  s.bands = (rows + band_rows - 1) / band_rows;
  s.file_base = file_bytes_;
  s.strips.resize(std::size_t(planes) * std::size_t(s.bands));
  file_bytes_ += std::uint64_t(planes) * std::uint64_t(s.bands) * std::uint64_t(band_rows) *
                 std::uint64_t(row_bytes);
  slabs_.push_back(std::move(s));
  return int(slabs_.size() - 1);
}

std::int64_t SpillStore::band_count(int slab) const {
  return slabs_[std::size_t(slab)].bands;
}

std::size_t SpillStore::band_bytes(const Slab& s, std::int64_t band) const {
  return std::size_t(std::min(s.band_rows, s.rows - band * s.band_rows)) * s.row_bytes;
}

std::uint64_t SpillStore::slot_offset(const Slab& s, int z, std::int64_t band) const {
  return s.file_base + (std::uint64_t(z) * std::uint64_t(s.bands) + std::uint64_t(band)) *
                           std::uint64_t(s.band_rows) * std::uint64_t(s.row_bytes);
}

void SpillStore::open_file() {
  if (fd_ >= 0) return;
  std::string pattern = near_path_ + ".spill.XXXXXX";
  fd_ = ::mkstemp(pattern.data());
  if (fd_ < 0)
    throw IoError(
        cat(pattern, ": cannot create the writer's scratch file: ", std::strerror(errno)));
  ::unlink(pattern.c_str());  // nameless from now on: nothing to clean up
}

void SpillStore::put_band(int slab, int z, std::int64_t band, const std::uint8_t* data,
                          ZSTD_CCtx* cctx, std::vector<std::uint8_t>& work) {
  Slab& s = slabs_[std::size_t(slab)];
  Strip& strip = s.strips[std::size_t(z) * std::size_t(s.bands) + std::size_t(band)];
  const std::size_t n = band_bytes(s, band);
  if (work.size() < ZSTD_compressBound(n)) work.resize(ZSTD_compressBound(n));
  const std::size_t c = ZSTD_compressCCtx(cctx, work.data(), work.size(), data, n, kStripLevel);
  if (ZSTD_isError(c)) throw Error(cat(what_, ": zstd failed: ", ZSTD_getErrorName(c)));
  const bool raw = c >= n;
  const std::uint8_t* bytes = raw ? data : work.data();
  const std::size_t size = raw ? n : c;
  std::lock_guard<std::mutex> lock(mutex_);
  memory_used_ -= strip.bytes.capacity();
  if (memory_used_ + std::max(size, strip.bytes.capacity()) <= memory_limit_) {
    strip.bytes.assign(bytes, bytes + size);
    strip.in_file = false;
    memory_used_ += strip.bytes.capacity();
  } else {
    std::vector<std::uint8_t>().swap(strip.bytes);
    open_file();
    pwrite_all(fd_, bytes, size, slot_offset(s, z, band), what_);
    strip.in_file = true;
  }
  strip.raw = raw;
  strip.size = size;
  strip.stored = true;
}

void SpillStore::get_band(int slab, int z, std::int64_t band, std::uint8_t* out) {
  Slab& s = slabs_[std::size_t(slab)];
  const Strip& strip = s.strips[std::size_t(z) * std::size_t(s.bands) + std::size_t(band)];
  if (!strip.stored)
    throw std::logic_error(cat(what_, ": band ", band, " of plane ", z, " was never stored"));
  const std::size_t n = band_bytes(s, band);
  const std::uint8_t* bytes = strip.bytes.data();
  if (strip.in_file) {
    std::uint8_t* dst = out;
    if (!strip.raw) {
      if (scratch_.size() < strip.size) scratch_.resize(strip.size);
      dst = scratch_.data();
    }
    pread_all(fd_, dst, strip.size, slot_offset(s, z, band), what_);
    bytes = dst;
  }
  if (strip.raw) {
    if (bytes != out) std::memcpy(out, bytes, n);
    return;
  }
  const std::size_t r = ZSTD_decompressDCtx(dctx_, out, n, bytes, strip.size);
  if (ZSTD_isError(r) || r != n)
    throw FormatError(cat(what_, ": band ", band, " of plane ", z, " does not decode"));
}

}  // namespace vispack::format::detail

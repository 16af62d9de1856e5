// A buffer for a brick row of slices (the format Writer's level-0 slab, a pack shard's slab):
// fresh anonymous pages (mmap), which the kernel maps to its one zero page until first written,
// that remember which of them hold only zero bytes. Writing zeros onto a page known to be zero is
// skipped, so such a page is never touched: no page fault, no memory. Outside the body a slice's
// colour and labels are zero (the pack zeroes the gel, docs/ARCHITECTURE.md, 'The packed file'):
// about 40 % of the 4 KiB pages of a 2048x1216 slice of the real-size stack, whose slab (~1.1 GB)
// was otherwise all faulted in on its first fill, and on a machine whose fresh pages are dear (a VM
// returning free memory to its host: docs/BENCHMARKS.md "Fresh memory") that cost about what zstd
// takes to compress the whole slab. Reading is plain memory access (untouched pages read as zero),
// but a read faults an untouched page in too (and on a kernel without a shared zero page,
// pvm_no_zero_page, allocates and clears it): readers that can skip zeros ask known_zero() first
// (the format's brick gather and 2x2x2 reduction do). Ownership: RAII (munmap). Thread-safety:
// write() and write_narrowed() may run at once on ranges that share no page (page_size()
// granularity, offsets from data()); reads of data() must not overlap a write.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>

namespace vispack {

class ZeroPagedBuffer {
 public:
  ZeroPagedBuffer() = default;
  // `size` bytes, all zero. Throws std::bad_alloc when the mapping fails.
  explicit ZeroPagedBuffer(std::size_t size);
  ~ZeroPagedBuffer();
  ZeroPagedBuffer(ZeroPagedBuffer&& other) noexcept;
  ZeroPagedBuffer& operator=(ZeroPagedBuffer&& other) noexcept;
  ZeroPagedBuffer(const ZeroPagedBuffer&) = delete;
  ZeroPagedBuffer& operator=(const ZeroPagedBuffer&) = delete;

  // Read-only: a byte written other than through write() would escape the zero-page record.
  const std::uint8_t* data() const { return data_; }
  std::size_t size() const { return size_; }
  static std::size_t page_size();
  // True when every page that [p, p + n) touches is known to hold only zeros (never written, or
  // last written with zeros): such bytes read as zero without being touched. False for n == 0 or a
  // range outside this buffer. Thread-safety: may run beside write() on pages it does not ask
  // about.
  bool known_zero(const std::uint8_t* p, std::size_t n) const;

  // data()[at, at + n) = src[0, n). A page wholly inside the range whose new bytes are all zero
  // is left untouched when it is known to be zero; the range's partly covered pages are copied.
  void write(std::size_t at, const std::uint8_t* src, std::size_t n);
  // data()[at + i] = std::uint8_t(src[i]) for i in [0, n) (uint16 label IDs that fit in uint8),
  // with the same skipping.
  void write_narrowed(std::size_t at, const std::uint16_t* src, std::size_t n);

 private:
  template <class T, class Copy>
  void write_pages(std::size_t at, const T* src, std::size_t n, Copy copy);

  std::uint8_t* data_ = nullptr;
  std::size_t size_ = 0;
  std::size_t mapped_ = 0;
  std::unique_ptr<std::uint8_t[]> page_zero_;  // 1: the page holds only zero bytes
};

}  // namespace vispack

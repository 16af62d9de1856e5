#include "vispack/common/zero_paged_buffer.h"

#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <new>
#include <type_traits>
#include <utility>

namespace vispack {
namespace {

// True when the n values at p are all zero (an OR over 8-byte words, which the compiler
// vectorises; p need not be aligned).
template <class T>
bool all_zero(const T* values, std::size_t n) {
  const auto* p = reinterpret_cast<const unsigned char*>(values);
  std::size_t bytes = n * sizeof(T);
  std::uint64_t acc = 0;
  std::size_t i = 0;
  for (; i + 32 <= bytes; i += 32) {
    std::uint64_t w[4];
    std::memcpy(w, p + i, sizeof w);
    acc |= w[0] | w[1] | w[2] | w[3];
  }
  for (; i < bytes; ++i)
    acc |= p[i];
  return acc == 0;
}

}  // namespace

std::size_t ZeroPagedBuffer::page_size() {
  static const std::size_t size = std::size_t(::sysconf(_SC_PAGESIZE));
  return size;
}

bool ZeroPagedBuffer::known_zero(const std::uint8_t* p, std::size_t n) const {
  if (n == 0 || !data_ || p < data_ || std::size_t(p - data_) > size_ ||
      n > size_ - std::size_t(p - data_))
    return false;
  const std::size_t page = page_size();
  const std::size_t first = std::size_t(p - data_) / page;
  const std::size_t last = (std::size_t(p - data_) + n - 1) / page;
  for (std::size_t i = first; i <= last; ++i)
    if (!page_zero_[i]) return false;
  return true;
}

ZeroPagedBuffer::ZeroPagedBuffer(std::size_t size) : size_(size) {
  if (size == 0) return;
  const std::size_t page = page_size();
  const std::size_t pages = (size + page - 1) / page;
  mapped_ = pages * page;
  void* p = ::mmap(nullptr, mapped_, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  if (p == MAP_FAILED) throw std::bad_alloc();
  data_ = static_cast<std::uint8_t*>(p);
  page_zero_ = std::make_unique<std::uint8_t[]>(pages);
  std::fill_n(page_zero_.get(), pages, std::uint8_t(1));
}

ZeroPagedBuffer::~ZeroPagedBuffer() {
  if (data_) ::munmap(data_, mapped_);
}

ZeroPagedBuffer::ZeroPagedBuffer(ZeroPagedBuffer&& other) noexcept
    : data_(std::exchange(other.data_, nullptr)),
      size_(std::exchange(other.size_, 0)),
      mapped_(std::exchange(other.mapped_, 0)),
      page_zero_(std::move(other.page_zero_)) {}

ZeroPagedBuffer& ZeroPagedBuffer::operator=(ZeroPagedBuffer&& other) noexcept {
  if (this != &other) {
    if (data_) ::munmap(data_, mapped_);
    data_ = std::exchange(other.data_, nullptr);
    size_ = std::exchange(other.size_, 0);
    mapped_ = std::exchange(other.mapped_, 0);
    page_zero_ = std::move(other.page_zero_);
  }
  return *this;
}

// Writes n values of src from byte `at` on, one output byte per value (uint8 copied, uint16
// narrowed), page by page: copy(dst, from, count) writes count values.
template <class T, class Copy>
void ZeroPagedBuffer::write_pages(std::size_t at, const T* src, std::size_t n, Copy copy) {
  static_assert(std::is_same_v<T, std::uint8_t> || std::is_same_v<T, std::uint16_t>);
  const std::size_t page = page_size();
  const std::size_t end = at + n;
  std::size_t pos = at;
  while (pos < end) {
    const std::size_t p = pos / page;
    const std::size_t page_end = std::min(end, (p + 1) * page);
    const std::size_t count = page_end - pos;
    const T* from = src + (pos - at);
    const bool whole = pos == p * page && page_end == (p + 1) * page;
    if (whole && all_zero(from, count)) {
      if (!page_zero_[p]) {
        std::memset(data_ + pos, 0, page_end - pos);
        page_zero_[p] = 1;
      }
    } else {
      copy(data_ + pos, from, count);
      page_zero_[p] = 0;
    }
    pos = page_end;
  }
}

void ZeroPagedBuffer::write(std::size_t at, const std::uint8_t* src, std::size_t n) {
  write_pages(at, src, n, [](std::uint8_t* dst, const std::uint8_t* from, std::size_t count) {
    std::memcpy(dst, from, count);
  });
}

void ZeroPagedBuffer::write_narrowed(std::size_t at, const std::uint16_t* src, std::size_t n) {
  write_pages(at, src, n, [](std::uint8_t* dst, const std::uint16_t* from, std::size_t count) {
    for (std::size_t i = 0; i < count; ++i)
      dst[i] = std::uint8_t(from[i]);
  });
}

}  // namespace vispack

#include "spill_store.h"

#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>

#include "vispack/common/error.h"

namespace vispack::format::detail {

SpillStore::SpillStore(std::uint64_t bytes, std::uint64_t memory_limit,
                       const std::string& near_path)
    : what_(near_path + " (scratch of the coarser levels)") {
  if (bytes <= memory_limit) {
    memory_.resize(std::size_t(bytes));
    return;
  }
  std::string pattern = near_path + ".spill.XXXXXX";
  fd_ = ::mkstemp(pattern.data());
  if (fd_ < 0)
    throw IoError(
        cat(pattern, ": cannot create the writer's scratch file: ", std::strerror(errno)));
  ::unlink(pattern.c_str());  // nameless from now on: nothing to clean up
}

SpillStore::~SpillStore() {
  if (fd_ >= 0) ::close(fd_);
}

void SpillStore::write(std::uint64_t offset, const void* data, std::size_t n) {
  if (fd_ < 0) {
    std::memcpy(memory_.data() + offset, data, n);
    return;
  }
  const auto* p = static_cast<const std::uint8_t*>(data);
  while (n > 0) {
    const ssize_t w = ::pwrite(fd_, p, n, off_t(offset));
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) throw IoError(cat(what_, ": write failed: ", std::strerror(errno)));
    p += w;
    n -= std::size_t(w);
    offset += std::uint64_t(w);
  }
}

void SpillStore::read(std::uint64_t offset, void* data, std::size_t n) const {
  if (fd_ < 0) {
    std::memcpy(data, memory_.data() + offset, n);
    return;
  }
  auto* p = static_cast<std::uint8_t*>(data);
  while (n > 0) {
    const ssize_t r = ::pread(fd_, p, n, off_t(offset));
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) throw IoError(cat(what_, ": read failed: ", r < 0 ? std::strerror(errno) : "EOF"));
    p += r;
    n -= std::size_t(r);
    offset += std::uint64_t(r);
  }
}

}  // namespace vispack::format::detail

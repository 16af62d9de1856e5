#include "vispack/common/atomic_file.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <vector>

#include "vispack/common/error.h"

namespace vispack {
namespace {

std::atomic<unsigned> g_temp_counter{0};  // distinguishes temp names within one process

std::string parent_dir(const std::string& path) {
  auto parent = std::filesystem::path(path).parent_path();
  return parent.empty() ? std::string(".") : parent.string();
}

void fsync_dir(const std::string& dir) {
  int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    ::fsync(fd);  // best effort: some filesystems refuse fsync on directories
    ::close(fd);
  }
}

}  // namespace

AtomicFile::AtomicFile(std::string path) : path_(std::move(path)) {
  temp_path_ = cat(path_, ".tmp-", ::getpid(), "-", g_temp_counter++);
  fd_ = ::open(temp_path_.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd_ < 0) {
    throw IoError(cat(path_, ": cannot create temporary file in ", parent_dir(path_), ": ",
                      std::strerror(errno)));
  }
}

AtomicFile::~AtomicFile() {
  if (fd_ >= 0) {
    ::close(fd_);
    ::unlink(temp_path_.c_str());
  }
}

void AtomicFile::write(const void* data, std::size_t size) {
  const char* bytes = static_cast<const char*>(data);
  while (size > 0) {
    ssize_t n = ::write(fd_, bytes, size);
    if (n < 0) {
      if (errno == EINTR) continue;
      throw IoError(cat(path_, ": write failed after ", size_, " bytes: ", std::strerror(errno)));
    }
    bytes += n;
    size -= std::size_t(n);
    size_ += std::uint64_t(n);
  }
}

void AtomicFile::append_from(int fd, std::uint64_t offset, std::uint64_t size,
                             const std::string& source, bool copy_range) {
  auto short_source = [&](std::uint64_t at) {
    return IoError(cat(source, ": ends at byte ", at, ", before ", offset + size,
                       " (the range being copied into ", path_, ")"));
  };
  while (size > 0 && copy_range) {
    loff_t in = loff_t(offset);
    const ssize_t n = ::copy_file_range(fd, &in, fd_, nullptr, std::size_t(size), 0);
    if (n < 0) {
      if (errno == EINTR) continue;
      // Refused for this pair of files (other file systems, an old kernel, a special file):
      // copied by hand below. Anything else is a real failure.
      if (errno == EXDEV || errno == EINVAL || errno == ENOSYS || errno == EOPNOTSUPP ||
          errno == EBADF || errno == ETXTBSY)
        copy_range = false;
      else
        throw IoError(cat(path_, ": copying ", size, " bytes from ", source, " failed after ",
                          size_, " bytes: ", std::strerror(errno)));
      break;
    }
    if (n == 0) throw short_source(offset);
    offset += std::uint64_t(n);
    size -= std::uint64_t(n);
    size_ += std::uint64_t(n);
  }
  if (size == 0) return;
  std::vector<char> buffer(std::size_t(std::min<std::uint64_t>(size, std::uint64_t(1) << 20)));
  while (size > 0) {
    const ssize_t n =
        ::pread(fd, buffer.data(), std::size_t(std::min<std::uint64_t>(size, buffer.size())),
                off_t(offset));
    if (n < 0) {
      if (errno == EINTR) continue;
      throw IoError(cat(source, ": read failed at byte ", offset, ": ", std::strerror(errno)));
    }
    if (n == 0) throw short_source(offset);
    write(buffer.data(), std::size_t(n));
    offset += std::uint64_t(n);
    size -= std::uint64_t(n);
  }
}

void AtomicFile::pwrite(const void* data, std::size_t size, std::uint64_t offset) {
  const char* bytes = static_cast<const char*>(data);
  while (size > 0) {
    ssize_t n = ::pwrite(fd_, bytes, size, off_t(offset));
    if (n < 0) {
      if (errno == EINTR) continue;
      throw IoError(cat(path_, ": write at offset ", offset, " failed: ", std::strerror(errno)));
    }
    bytes += n;
    size -= std::size_t(n);
    offset += std::uint64_t(n);
  }
}

void AtomicFile::commit() {
  if (fd_ < 0) throw IoError(cat(path_, ": commit on a closed file"));
  if (::fsync(fd_) != 0) {
    throw IoError(cat(path_, ": fsync failed: ", std::strerror(errno)));
  }
  if (::close(fd_) != 0) {
    fd_ = -1;
    ::unlink(temp_path_.c_str());
    throw IoError(cat(path_, ": close failed: ", std::strerror(errno)));
  }
  fd_ = -1;
  if (::rename(temp_path_.c_str(), path_.c_str()) != 0) {
    int err = errno;
    ::unlink(temp_path_.c_str());
    throw IoError(cat(path_, ": cannot rename temporary file into place: ", std::strerror(err)));
  }
  fsync_dir(parent_dir(path_));
}

void write_file_atomic(const std::string& path, const void* data, std::size_t size) {
  AtomicFile file(path);
  file.write(data, size);
  file.commit();
}

std::string read_file(const std::string& path, std::size_t max_bytes) {
  int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw IoError(cat(path, ": cannot open: ", std::strerror(errno)));
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    throw IoError(cat(path, ": not a regular file"));
  }
  if (std::uint64_t(st.st_size) > max_bytes) {
    ::close(fd);
    throw IoError(cat(path, ": file is ", st.st_size, " bytes, over the limit of ", max_bytes));
  }
  std::string out(std::size_t(st.st_size), '\0');
  std::size_t got = 0;
  while (got < out.size()) {
    ssize_t n = ::read(fd, out.data() + got, out.size() - got);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      int err = errno;
      ::close(fd);
      throw IoError(cat(path, ": read failed at byte ", got, n == 0 ? ": file shrank" : ": ",
                        n == 0 ? "" : std::strerror(err)));
    }
    got += std::size_t(n);
  }
  ::close(fd);
  return out;
}

void make_directories(const std::string& path) {
  std::error_code ec;
  std::filesystem::create_directories(path, ec);
  if (ec) throw IoError(cat(path, ": cannot create directory: ", ec.message()));
}

}  // namespace vispack

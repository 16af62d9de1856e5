// WorkFolderLock: a POSIX record lock on WORK/.vispack.lock (work_lock.h).
#include "vispack/pipeline/core/work_lock.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <limits>

#include "vispack/common/busy_error.h"
#include "vispack/common/error.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

namespace {

// The byte range a run locks: [start, start + length), length 0 = to the end of any file.
struct Range {
  off_t start = 0;
  off_t length = 0;
};

// --slices "A:B" as stack indices (either side may be empty); "" = the whole stack.
bool shard_range(const std::string& slices, Range& range) {
  if (slices.empty()) return false;
  const std::size_t colon = slices.find(':');
  if (colon == std::string::npos) throw UsageError(cat("--slices \"", slices, "\" is not A:B"));
  auto index = [&](const std::string& text, long long fallback) {
    if (text.empty()) return fallback;
    try {
      std::size_t used = 0;
      const long long v = std::stoll(text, &used);
      if (used != text.size() || v < 0) throw std::invalid_argument(text);
      return v;
    } catch (const std::exception&) {
      throw UsageError(cat("--slices \"", slices, "\" is not A:B (stack indices)"));
    }
  };
  const long long first = index(slices.substr(0, colon), 0);
  const long long last = index(slices.substr(colon + 1), -1);
  range.start = off_t(1 + first);
  range.length = last < 0 ? 0 : off_t(std::max(1LL, last - first));
  return true;
}

// Tries one lock; returns 0, or the pid holding a conflicting one (-1 when unknown), or throws.
int try_lock(int fd, short type, Range range, const std::string& path, bool& unsupported) {
  struct flock lock {};
  lock.l_type = type;
  lock.l_whence = SEEK_SET;
  lock.l_start = range.start;
  lock.l_len = range.length;
  for (int attempt = 0; attempt < 3; ++attempt) {
    if (::fcntl(fd, F_SETLK, &lock) == 0) return 0;
    const int error = errno;
    if (error == EINTR) continue;
    if (error == ENOLCK || error == EOPNOTSUPP || error == ENOSYS || error == EINVAL) {
      unsupported = true;
      return 0;
    }
    if (error != EAGAIN && error != EACCES)
      throw IoError(cat(path, ": cannot lock: ", std::strerror(error)));
    struct flock holder = lock;
    if (::fcntl(fd, F_GETLK, &holder) != 0) return -1;
    if (holder.l_type == F_UNLCK) continue;  // the holder just ended: try again
    return holder.l_pid > 0 ? int(holder.l_pid) : -1;
  }
  return -1;
}

}  // namespace

WorkFolderLock WorkFolderLock::acquire(const std::string& work_dir, const std::string& slices) {
  std::error_code ec;
  fs::create_directories(work_dir, ec);
  if (ec) throw IoError(cat(work_dir, ": cannot create the work folder: ", ec.message()));
  const std::string path = (fs::path(work_dir) / kWorkLockFile).string();
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) throw IoError(cat(path, ": cannot open the lock file: ", std::strerror(errno)));
  WorkFolderLock result(fd, path);

  Range shard;
  const bool sharded = shard_range(slices, shard);
  bool unsupported = false;
  int holder = 0;
  if (sharded) {
    holder = try_lock(fd, F_RDLCK, Range{0, 1}, path, unsupported);
    if (holder == 0 && !unsupported) holder = try_lock(fd, F_WRLCK, shard, path, unsupported);
  } else {
    holder = try_lock(fd, F_WRLCK, Range{0, 0}, path, unsupported);
  }
  if (unsupported) {
    std::cerr << "warning: " << path
              << ": this file system has no record locks; nothing keeps a second run off this "
                 "work folder\n";
    return result;
  }
  if (holder != 0) {
    throw BusyError(
        cat(work_dir, ": work folder in use by another vispack run (",
            holder > 0 ? cat("process ", holder) : std::string("a process on another machine"),
            sharded ? cat(", holding this shard's slices or the whole folder") : std::string(),
            "); wait for it to end, or give this run another work_dir"));
  }
  return result;
}

WorkFolderLock::WorkFolderLock(WorkFolderLock&& other) noexcept
    : fd_(other.fd_), path_(std::move(other.path_)) {
  other.fd_ = -1;
}

WorkFolderLock::~WorkFolderLock() {
  if (fd_ >= 0) ::close(fd_);
}

}  // namespace vispack::pipeline

// Keeps two runs off one work folder (README.md "Exit codes", docs/ARCHITECTURE.md "Work folder
// layout"): two processes writing the same intermediates race on their temporary files and one
// of them fails half way.
//
// The lock is a POSIX record lock (fcntl) on WORK/.vispack.lock. The kernel drops it when the
// process ends however it ends (crash, kill -9), so a dead run never leaves the folder locked:
// the file stays behind and means nothing by itself. A record lock rather than flock(): the
// kernel reports the holder's process id (F_GETLK), and it also works on NFS.
//   - a whole-stack run locks the whole file, exclusively;
//   - a shard (`--slices A:B`, a cluster) locks byte 0 shared and bytes [1 + A, 1 + B)
//     exclusively, so shards of disjoint ranges run side by side on one shared work folder, while
//     a whole run and a shard, or two shards that overlap, exclude each other.
// The lock belongs to the process (POSIX record-lock semantics): a second lock of the same folder
// in the same process succeeds. Not thread-safe; one per process.
#pragma once

#include <string>

namespace vispack::pipeline {

class WorkFolderLock {
 public:
  // Locks `work_dir` (created when missing) for a whole run (`slices` empty) or for the shard
  // `slices` ("A:B", either side may be empty, as --slices). Throws BusyError naming the folder
  // and the holder's process id when another process holds a conflicting lock, IoError when the
  // lock file cannot be made. On a file system without record locks it warns on stderr and
  // locks nothing.
  static WorkFolderLock acquire(const std::string& work_dir, const std::string& slices = "");

  WorkFolderLock(WorkFolderLock&& other) noexcept;
  WorkFolderLock& operator=(WorkFolderLock&&) = delete;
  WorkFolderLock(const WorkFolderLock&) = delete;
  WorkFolderLock& operator=(const WorkFolderLock&) = delete;
  ~WorkFolderLock();  // closes the file, which releases the lock

  // The lock file's path.
  const std::string& path() const { return path_; }

 private:
  WorkFolderLock(int fd, std::string path) : fd_(fd), path_(std::move(path)) {}
  int fd_ = -1;
  std::string path_;
};

// The lock file's name inside a work folder.
inline constexpr const char* kWorkLockFile = ".vispack.lock";

}  // namespace vispack::pipeline

// Files that appear complete or not at all.
//
// AtomicFile writes to a temporary name beside the destination ("<path>.tmp-<pid>-<n>"),
// and commit() flushes, fsyncs, renames onto the destination and fsyncs the directory.
// If commit() is never called (an exception, an early return), the destructor removes the
// temporary file, so the destination keeps its previous content (or stays absent).
// Not thread-safe: one AtomicFile belongs to one thread at a time.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace vispack {

class AtomicFile {
 public:
  // Creates the temporary file. Throws IoError naming `path` if it cannot.
  explicit AtomicFile(std::string path);
  ~AtomicFile();
  AtomicFile(const AtomicFile&) = delete;
  AtomicFile& operator=(const AtomicFile&) = delete;

  // Appends bytes. Throws IoError (disk full, file too large) naming the destination.
  void write(const void* data, std::size_t size);
  void write(std::string_view text) { write(text.data(), text.size()); }
  // Appends `size` bytes at `offset` of the open file `fd` (`source` names it in errors):
  // copy_file_range, so the bytes go from file to file inside the kernel, else (file systems or
  // kernels that refuse it) pread and write through a 1 MiB buffer; `copy_range` false takes the
  // second way from the start. Throws IoError naming `source` when it ends before offset + size,
  // or the destination on a write failure.
  void append_from(int fd, std::uint64_t offset, std::uint64_t size, const std::string& source,
                   bool copy_range = true);
  // Writes at an absolute offset (for patching a header); does not move the append position.
  void pwrite(const void* data, std::size_t size, std::uint64_t offset);
  // Bytes appended so far.
  std::uint64_t size() const { return size_; }
  // fsync + rename + directory fsync. After commit() the object is inert.
  void commit();

  const std::string& path() const { return path_; }
  const std::string& temp_path() const { return temp_path_; }
  int fd() const { return fd_; }

 private:
  std::string path_;
  std::string temp_path_;
  int fd_ = -1;
  std::uint64_t size_ = 0;
};

// Writes `bytes` to `path` atomically. Throws IoError.
void write_file_atomic(const std::string& path, const void* data, std::size_t size);
inline void write_file_atomic(const std::string& path, std::string_view text) {
  write_file_atomic(path, text.data(), text.size());
}

// Reads a whole file. Throws IoError naming the path. Refuses files over `max_bytes`.
std::string read_file(const std::string& path, std::size_t max_bytes = std::size_t(1) << 32);

// Creates a directory and its parents (like mkdir -p). Throws IoError.
void make_directories(const std::string& path);

}  // namespace vispack

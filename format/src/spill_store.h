// Internal to the format writer: a fixed-size scratch area addressed by byte offset, held in
// memory when small and otherwise in an unlinked temporary file beside the output, so that its
// bytes live in the page cache, not in the process's resident memory. The Writer keeps the
// partly filled slabs of the coarser pyramid levels here (writer.h, "Memory").
// Ownership: RAII; the file has no name once created (unlinked at once), so nothing is left
// behind, whatever happens. Thread-safety: one thread at a time.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace vispack::format::detail {

class SpillStore {
 public:
  // `bytes` of scratch; in memory when bytes <= memory_limit, else in a temporary file created
  // next to `near_path` (IoError naming it if it cannot be created).
  SpillStore(std::uint64_t bytes, std::uint64_t memory_limit, const std::string& near_path);
  ~SpillStore();
  SpillStore(const SpillStore&) = delete;
  SpillStore& operator=(const SpillStore&) = delete;

  // Copies n bytes in / out at `offset` (offset + n <= bytes). Throws IoError on a failed
  // write (disk full) or read.
  void write(std::uint64_t offset, const void* data, std::size_t n);
  void read(std::uint64_t offset, void* data, std::size_t n) const;

  bool in_file() const { return fd_ >= 0; }

 private:
  std::string what_;  // names the store in errors
  std::vector<std::uint8_t> memory_;
  int fd_ = -1;
};

}  // namespace vispack::format::detail

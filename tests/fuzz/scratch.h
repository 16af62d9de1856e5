// Scratch folder for fuzz targets whose entry point takes a path (see fuzz_target.h).
#pragma once

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <string>

#include "test_support.h"

inline const std::string& vispack_fuzz_scratch_dir() {
  // One per process (libFuzzer calls the target repeatedly), removed at exit.
  static const vispack::test::TempDir scratch("vispack-fuzz");
  return scratch.path();
}

// Writes `size` bytes to `path` (plain write: the fuzz input, not a vispack output).
inline void vispack_fuzz_write(const std::string& path, const void* data, std::size_t size) {
  FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) std::abort();
  if (size) std::fwrite(data, 1, size, f);
  std::fclose(f);
}

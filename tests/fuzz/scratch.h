// Scratch folder for fuzz targets whose entry point takes a path (see fuzz_target.h).
#pragma once

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <string>

inline const std::string& vispack_fuzz_scratch_dir() {
  struct Scratch {
    std::string path;
    Scratch() {
      const char* tmp = std::getenv("TMPDIR");
      std::string pattern = std::string(tmp && *tmp ? tmp : "/tmp") + "/vispack-fuzz-XXXXXX";
      if (::mkdtemp(pattern.data()) == nullptr) std::abort();
      path = pattern;
    }
    ~Scratch() {
      std::error_code ec;
      std::filesystem::remove_all(path, ec);
    }
  };
  static Scratch scratch;  // one per process: libFuzzer calls the target repeatedly
  return scratch.path;
}

// Writes `size` bytes to `path` (plain write: the fuzz input, not a vispack output).
inline void vispack_fuzz_write(const std::string& path, const void* data, std::size_t size) {
  FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) std::abort();
  if (size) std::fwrite(data, 1, size, f);
  std::fclose(f);
}

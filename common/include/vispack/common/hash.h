// Hashes for checksums and provenance (xxHash64, seed 0).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

namespace vispack {

std::uint64_t xxh64(const void* data, std::size_t size, std::uint64_t seed = 0);
// xxHash64 of a whole file, streamed. Throws IoError naming the path.
std::uint64_t xxh64_file(const std::string& path);

// xxHash64 (seed 0) of bytes handed over piece by piece: the digest equals xxh64 of the pieces
// concatenated. Ownership: RAII. Not thread-safe (one object, one thread at a time).
class Xxh64Stream {
 public:
  Xxh64Stream();  // throws std::bad_alloc
  ~Xxh64Stream();
  Xxh64Stream(const Xxh64Stream&) = delete;
  Xxh64Stream& operator=(const Xxh64Stream&) = delete;
  void update(const void* data, std::size_t size);
  std::uint64_t digest() const;

 private:
  struct State;
  std::unique_ptr<State> state_;
};

// 16 lowercase hex digits.
std::string hex64(std::uint64_t value);

}  // namespace vispack

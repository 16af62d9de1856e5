// Hashes for checksums and provenance (xxHash64, seed 0).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

namespace vispack {

std::uint64_t xxh64(const void* data, std::size_t size, std::uint64_t seed = 0);
// xxHash64 of a whole file, streamed. Throws IoError naming the path.
std::uint64_t xxh64_file(const std::string& path);
// 16 lowercase hex digits.
std::string hex64(std::uint64_t value);

}  // namespace vispack

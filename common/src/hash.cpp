#include "vispack/common/hash.h"

#include <xxhash.h>

#include <cstdio>
#include <cstring>
#include <memory>
#include <vector>

#include "vispack/common/error.h"

namespace vispack {

std::uint64_t xxh64(const void* data, std::size_t size, std::uint64_t seed) {
  return XXH64(data, size, seed);
}

std::uint64_t xxh64_file(const std::string& path) {
  std::unique_ptr<FILE, int (*)(FILE*)> file(std::fopen(path.c_str(), "rb"), &std::fclose);
  if (!file) throw IoError(cat(path, ": cannot open: ", std::strerror(errno)));
  std::unique_ptr<XXH64_state_t, XXH_errorcode (*)(XXH64_state_t*)> state(XXH64_createState(),
                                                                          &XXH64_freeState);
  XXH64_reset(state.get(), 0);
  std::vector<char> buffer(1 << 20);
  for (;;) {
    std::size_t n = std::fread(buffer.data(), 1, buffer.size(), file.get());
    if (n > 0) XXH64_update(state.get(), buffer.data(), n);
    if (n < buffer.size()) {
      if (std::ferror(file.get())) throw IoError(cat(path, ": read failed"));
      break;
    }
  }
  return XXH64_digest(state.get());
}

std::string hex64(std::uint64_t value) {
  char text[17];
  std::snprintf(text, sizeof text, "%016llx", static_cast<unsigned long long>(value));
  return text;
}

}  // namespace vispack

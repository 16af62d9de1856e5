#include "vispack/common/hash.h"

#include <xxhash.h>

#include <cstdio>
#include <cstring>
#include <memory>
#include <new>
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

struct Xxh64Stream::State {
  XXH64_state_t* xxh = nullptr;
};

Xxh64Stream::Xxh64Stream() : state_(std::make_unique<State>()) {
  state_->xxh = XXH64_createState();
  if (!state_->xxh) throw std::bad_alloc();
  XXH64_reset(state_->xxh, 0);
}

Xxh64Stream::~Xxh64Stream() {
  XXH64_freeState(state_->xxh);
}

void Xxh64Stream::update(const void* data, std::size_t size) {
  if (size > 0) XXH64_update(state_->xxh, data, size);
}

std::uint64_t Xxh64Stream::digest() const {
  return XXH64_digest(state_->xxh);
}

std::string hex64(std::uint64_t value) {
  char text[17];
  std::snprintf(text, sizeof text, "%016llx", static_cast<unsigned long long>(value));
  return text;
}

}  // namespace vispack

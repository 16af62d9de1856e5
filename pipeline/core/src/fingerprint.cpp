#include "vispack/pipeline/core/fingerprint.h"

#include <sys/stat.h>

#include <cstdio>

#include "vispack/common/error.h"
#include "vispack/common/hash.h"

namespace vispack::pipeline {

std::string file_identity(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return "";
  long long ns = (long long)st.st_mtim.tv_sec * 1000000000LL + st.st_mtim.tv_nsec;
  return cat((long long)st.st_size, ":", ns);
}

Fingerprint& Fingerprint::file(const std::string& path) {
  std::string id = file_identity(path);
  data_ += cat("F", path, "\n", id.empty() ? "missing" : id, "\n");
  return *this;
}

Fingerprint& Fingerprint::content(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) {
    data_ += cat("C", path, "\nmissing\n");
    return *this;
  }
  data_ += cat("C", path, "\n", hex64(xxh64_file(path)), "\n");
  return *this;
}

Fingerprint& Fingerprint::text(const std::string& value) {
  data_ += cat("T", value.size(), ":", value, "\n");
  return *this;
}

Fingerprint& Fingerprint::number(double value) {
  char buffer[64];
  std::snprintf(buffer, sizeof buffer, "%.17g", value);
  data_ += cat("N", buffer, "\n");
  return *this;
}

std::string Fingerprint::str() const {
  return hex64(xxh64(data_.data(), data_.size()));
}

}  // namespace vispack::pipeline

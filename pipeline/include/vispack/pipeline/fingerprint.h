// Fingerprints for resume: an xxHash64 over file identities (path, size, mtime) and strings, so a
// stage can tell whether its inputs changed since it last ran. Thread-safety: a Fingerprint is a
// value (one thread at a time); file_identity is thread-safe.
#pragma once

#include <string>

namespace vispack::pipeline {

// Fingerprint builder: an xxHash64 over file identities (path, size, mtime in ns) and strings.
// A missing file contributes "missing" (so its later appearance changes the fingerprint).
class Fingerprint {
 public:
  Fingerprint& file(const std::string& path);
  Fingerprint& text(const std::string& value);
  Fingerprint& number(double value);
  std::string str() const;  // 16 hex digits
 private:
  std::string data_;
};

// "size:mtime_ns" of a file, or "" when it does not exist. Throws nothing.
std::string file_identity(const std::string& path);

}  // namespace vispack::pipeline

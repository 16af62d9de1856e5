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
  // A small file by its bytes (path and xxHash64 of the contents), not its mtime: for
  // files that several shards may each rewrite with the same bytes (transforms.json, which
  // every per-slice shard's register run solves and writes when it differs), so that a rewrite
  // of the same bytes leaves every fingerprint that names it as it was. Reads the whole file;
  // throws IoError when it exists and cannot be read.
  Fingerprint& content(const std::string& path);
  Fingerprint& text(const std::string& value);
  Fingerprint& number(double value);
  std::string str() const;  // 16 hex digits
 private:
  std::string data_;
};

// "size:mtime_ns" of a file, or "" when it does not exist. Throws nothing.
std::string file_identity(const std::string& path);

}  // namespace vispack::pipeline

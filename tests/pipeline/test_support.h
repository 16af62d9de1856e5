// Helpers shared by the pipeline tests: a fresh temporary folder per test, running executables.
#pragma once

#include <string>

namespace vispack::test {

// A new empty folder under $TMPDIR (or /tmp), removed when the object dies unless
// VISPACK_KEEP_TEST_DIRS is set.
class TempDir {
 public:
  explicit TempDir(const std::string& prefix = "vispack-test");
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::string& path() const { return path_; }
  std::string operator/(const std::string& name) const { return path_ + "/" + name; }

 private:
  std::string path_;
};

// Runs a shell command; returns its exit status (0..255), and its stdout+stderr in *output.
int run_command(const std::string& command, std::string* output = nullptr);

// Absolute path of an executable in build/bin ("vispack-phantom").
std::string bin(const std::string& name);

}  // namespace vispack::test

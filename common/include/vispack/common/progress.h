// Progress reporting for long work: a redrawn bar when stderr is a terminal, and plain
// "<label>: 40/160 slices (25%) 3.1 slices/s" lines otherwise (at most one per ~10% or 5 s),
// so logs stay readable. Thread-safe: workers may call advance() concurrently.
#pragma once

#include <chrono>
#include <cstdint>
#include <mutex>
#include <string>

namespace vispack {

class Progress {
 public:
  // `total` units of work named `unit` ("slices", "bricks"). `quiet` prints nothing.
  Progress(std::string label, std::int64_t total, std::string unit, bool quiet = false);
  ~Progress();  // finishes the line
  Progress(const Progress&) = delete;
  Progress& operator=(const Progress&) = delete;

  void advance(std::int64_t units = 1);
  void finish();
  double elapsed_seconds() const;

 private:
  void draw(bool final_line);
  std::string label_, unit_;
  std::int64_t total_, done_ = 0;
  bool quiet_, tty_, finished_ = false;
  int last_percent_printed_ = -1;
  std::chrono::steady_clock::time_point start_, last_print_;
  std::mutex mutex_;
};

}  // namespace vispack

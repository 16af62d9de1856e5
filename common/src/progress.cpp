#include "vispack/common/progress.h"

#include <unistd.h>

#include <cstdio>

namespace vispack {

Progress::Progress(std::string label, std::int64_t total, std::string unit, bool quiet)
    : label_(std::move(label)),
      unit_(std::move(unit)),
      total_(total),
      quiet_(quiet),
      tty_(::isatty(STDERR_FILENO) == 1),
      start_(std::chrono::steady_clock::now()),
      last_print_(start_) {}

Progress::~Progress() {
  finish();
}

double Progress::elapsed_seconds() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

void Progress::advance(std::int64_t units) {
  std::lock_guard<std::mutex> lock(mutex_);
  done_ += units;
  draw(false);
}

void Progress::finish() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (finished_) return;
  finished_ = true;
  draw(true);
}

void Progress::draw(bool final_line) {
  if (quiet_) return;
  auto now = std::chrono::steady_clock::now();
  int percent = total_ > 0 ? int(100 * done_ / total_) : 100;
  double seconds = std::chrono::duration<double>(now - start_).count();
  double rate = seconds > 0 ? double(done_) / seconds : 0.0;
  if (tty_) {
    if (!final_line && std::chrono::duration<double>(now - last_print_).count() < 0.1) return;
    last_print_ = now;
    const int width = 30;
    int filled = total_ > 0 ? int(width * done_ / total_) : width;
    std::fprintf(stderr, "\r%s [%.*s%*s] %lld/%lld %s %.1f %s/s", label_.c_str(), filled,
                 "##############################", width - filled, "", (long long)done_,
                 (long long)total_, unit_.c_str(), rate, unit_.c_str());
    if (final_line) std::fprintf(stderr, " (%.1f s)\n", seconds);
    std::fflush(stderr);
    return;
  }
  bool step = percent / 10 != last_percent_printed_ / 10;
  bool slow = std::chrono::duration<double>(now - last_print_).count() >= 5.0;
  if (!final_line && !step && !slow) return;
  if (final_line && last_percent_printed_ == 100) return;
  last_percent_printed_ = percent;
  last_print_ = now;
  std::fprintf(stderr, "%s: %lld/%lld %s (%d%%) %.1f %s/s\n", label_.c_str(), (long long)done_,
               (long long)total_, unit_.c_str(), percent, rate, unit_.c_str());
}

}  // namespace vispack

#include "vispack/common/background_writer.h"

#include <utility>

namespace vispack {

BackgroundWriter::BackgroundWriter(AtomicFile& file, bool background, std::size_t buffer_bytes)
    : file_(file), buffer_bytes_(buffer_bytes < 4096 ? 4096 : buffer_bytes) {
  buffer_.resize(buffer_bytes_);
  setp(buffer_.data(), buffer_.data() + buffer_.size());
  if (background) thread_ = std::thread([this] { run(); });
}

BackgroundWriter::~BackgroundWriter() {
  if (thread_.joinable()) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    changed_.notify_all();
    thread_.join();
  }
}

void BackgroundWriter::run() {
  std::unique_lock<std::mutex> lock(mutex_);
  for (;;) {
    changed_.wait(lock, [&] { return stop_ || !queue_.empty(); });
    if (queue_.empty()) return;  // stop_ and nothing left
    Chunk chunk = std::move(queue_.front());
    queue_.pop_front();
    writing_ = true;
    const bool failed = bool(error_);
    lock.unlock();
    std::exception_ptr error;
    if (!failed) {
      try {
        file_.pwrite(chunk.bytes.data(), chunk.bytes.size(), chunk.offset);
      } catch (...) {
        error = std::current_exception();
      }
    }
    lock.lock();
    if (error && !error_) error_ = error;
    writing_ = false;
    spare_.push_back(std::move(chunk.bytes));
    changed_.notify_all();
  }
}

bool BackgroundWriter::hand_over() {
  const std::size_t used = std::size_t(pptr() - pbase());
  const std::uint64_t offset = base_;
  base_ += used;
  bool ok = true;
  if (!thread_.joinable()) {
    if (!error_ && used > 0) {
      try {
        file_.pwrite(buffer_.data(), used, offset);
      } catch (...) {
        error_ = std::current_exception();
      }
    }
    ok = !error_;
  } else {
    std::unique_lock<std::mutex> lock(mutex_);
    changed_.wait(lock, [&] { return error_ || queue_.size() < 2; });
    ok = !error_;
    if (ok && used > 0) {
      buffer_.resize(used);
      queue_.push_back(Chunk{std::move(buffer_), offset});
      buffer_ = std::vector<char>();
      if (!spare_.empty()) {
        buffer_ = std::move(spare_.back());
        spare_.pop_back();
      }
      changed_.notify_all();
    }
  }
  if (!ok) {
    setp(nullptr, nullptr);  // every later write comes back here and fails
    return false;
  }
  buffer_.resize(buffer_bytes_);
  setp(buffer_.data(), buffer_.data() + buffer_.size());
  return true;
}

void BackgroundWriter::wait_idle() {
  if (!thread_.joinable()) return;
  std::unique_lock<std::mutex> lock(mutex_);
  changed_.wait(lock, [&] { return queue_.empty() && !writing_; });
}

BackgroundWriter::int_type BackgroundWriter::overflow(int_type ch) {
  if (!hand_over()) return traits_type::eof();
  if (traits_type::eq_int_type(ch, traits_type::eof())) return traits_type::not_eof(ch);
  *pptr() = traits_type::to_char_type(ch);
  pbump(1);
  return ch;
}

BackgroundWriter::pos_type BackgroundWriter::seekoff(off_type off, std::ios_base::seekdir dir,
                                                     std::ios_base::openmode which) {
  const pos_type failed(off_type(-1));
  if (!(which & std::ios_base::out)) return failed;
  const std::uint64_t now = base_ + std::uint64_t(pptr() - pbase());
  std::int64_t target = 0;
  if (dir == std::ios_base::beg) {
    target = off;
  } else if (dir == std::ios_base::cur) {
    target = std::int64_t(now) + off;
  } else {
    return failed;  // the end of the file is not tracked
  }
  if (target < 0) return failed;
  if (std::uint64_t(target) == now) return pos_type(off_type(now));
  if (!hand_over()) return failed;
  base_ = std::uint64_t(target);
  return pos_type(off_type(target));
}

BackgroundWriter::pos_type BackgroundWriter::seekpos(pos_type pos, std::ios_base::openmode which) {
  return seekoff(off_type(pos), std::ios_base::beg, which);
}

int BackgroundWriter::sync() {
  if (!hand_over()) return -1;
  wait_idle();
  std::lock_guard<std::mutex> lock(mutex_);
  return error_ ? -1 : 0;
}

void BackgroundWriter::finish() {
  hand_over();
  wait_idle();
  std::exception_ptr error;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    error = error_;
  }
  if (error) std::rethrow_exception(error);
}

}  // namespace vispack

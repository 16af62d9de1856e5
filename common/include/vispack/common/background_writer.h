// An std::streambuf that writes into an AtomicFile with the write system calls on a background
// thread, so that a producer serialising a large file (OpenVDB's Archive::write) overlaps its
// own work with the kernel's copying into the page cache.
//
// Bytes are collected in a buffer of `buffer_bytes`; a full buffer is handed to the background
// thread, which writes it with AtomicFile::pwrite at the offset it belongs to, while the
// producer fills the next one (at most two wait and one is written: memory <= 4 x buffer_bytes).
// Seeking (seekp to an earlier position to patch an offset, then back) hands the buffered bytes
// over and continues at the new position; the background thread writes the chunks in the order
// they were handed over, so a later patch lands after the bytes it overwrites. tellp() costs
// nothing.
// With `background` false the chunks are written on the calling thread (one core).
//
// Errors: a failing write (disk full, file too large) stops the writing; further output fails
// (the ostream's badbit) and finish() rethrows the IoError, which names the file and offset.
// The destructor joins the thread and drops any error (call finish() to see it).
// Thread-safety: one producer thread; the background thread is internal.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <exception>
#include <mutex>
#include <streambuf>
#include <thread>
#include <vector>

#include "vispack/common/atomic_file.h"

namespace vispack {

class BackgroundWriter : public std::streambuf {
 public:
  BackgroundWriter(AtomicFile& file, bool background, std::size_t buffer_bytes = 8u << 20);
  ~BackgroundWriter() override;
  BackgroundWriter(const BackgroundWriter&) = delete;
  BackgroundWriter& operator=(const BackgroundWriter&) = delete;

  // Writes what is buffered, waits for every write and rethrows the first write error.
  void finish();

 protected:
  int_type overflow(int_type ch) override;
  pos_type seekoff(off_type off, std::ios_base::seekdir dir,
                   std::ios_base::openmode which) override;
  pos_type seekpos(pos_type pos, std::ios_base::openmode which) override;
  int sync() override;

 private:
  struct Chunk {
    std::vector<char> bytes;
    std::uint64_t offset = 0;
  };
  // Queues [pbase, pptr) at base_ (or writes it, without the thread), starts a fresh buffer.
  // False once a write has failed.
  bool hand_over();
  void wait_idle();
  void run();

  AtomicFile& file_;
  const std::size_t buffer_bytes_;
  std::vector<char> buffer_;
  std::uint64_t base_ = 0;  // file offset of buffer_[0]
  std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<Chunk> queue_;
  std::vector<std::vector<char>> spare_;
  bool writing_ = false;
  bool stop_ = false;
  std::exception_ptr error_;
  std::thread thread_;
};

}  // namespace vispack

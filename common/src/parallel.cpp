#include "vispack/common/parallel.h"

#include <atomic>
#include <cstdlib>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

namespace vispack {

int resolve_threads(int requested) {
  if (requested > 0) return requested;
  if (const char* env = std::getenv("VISPACK_THREADS")) {
    int n = std::atoi(env);
    if (n > 0) return n;
  }
  unsigned hw = std::thread::hardware_concurrency();
  return hw > 0 ? int(hw) : 1;
}

void parallel_for(std::int64_t count, int threads, const std::function<void(std::int64_t)>& fn) {
  if (count <= 0) return;
  threads = resolve_threads(threads);
  if (threads <= 1 || count == 1) {
    for (std::int64_t i = 0; i < count; ++i)
      fn(i);
    return;
  }
  std::atomic<std::int64_t> next{0};
  std::atomic<bool> failed{false};
  std::exception_ptr first_error;
  std::mutex error_mutex;
  auto worker = [&] {
    for (;;) {
      if (failed.load(std::memory_order_relaxed)) return;
      std::int64_t i = next.fetch_add(1);
      if (i >= count) return;
      try {
        fn(i);
      } catch (...) {
        std::lock_guard<std::mutex> lock(error_mutex);
        if (!first_error) first_error = std::current_exception();
        failed = true;
        return;
      }
    }
  };
  int n = int(std::min<std::int64_t>(threads, count));
  std::vector<std::thread> pool;
  pool.reserve(std::size_t(n - 1));
  for (int t = 1; t < n; ++t)
    pool.emplace_back(worker);
  worker();
  for (auto& thread : pool)
    thread.join();
  if (first_error) std::rethrow_exception(first_error);
}

}  // namespace vispack

// Work spread over all cores without global state.
#pragma once

#include <cstdint>
#include <functional>

namespace vispack {

// Number of worker threads to use: `requested` if > 0, else std::thread::hardware_concurrency()
// (at least 1). The environment variable VISPACK_THREADS, if set, overrides the default.
int resolve_threads(int requested = 0);

// Calls fn(i) for every i in [0, count) on up to `threads` threads (dynamic scheduling, one
// index at a time). The first exception thrown by any call stops the remaining work and is
// rethrown on the calling thread after all workers have joined. fn must be thread-safe.
void parallel_for(std::int64_t count, int threads, const std::function<void(std::int64_t)>& fn);

}  // namespace vispack

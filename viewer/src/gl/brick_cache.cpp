#include "vispack/viewer/brick_cache.h"

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <exception>
#include <mutex>
#include <thread>
#include <unordered_map>
#include <unordered_set>

#include "texture_format.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/render/brick_reader.h"
#include "vispack/render/reference.h"

namespace vispack::viewer {

using render::BrickKey;
using render::Channel;

namespace {
struct JobKey {
  BrickKey key;
  Channel channel;
  bool operator==(const JobKey& o) const { return key == o.key && channel == o.channel; }
};
struct JobKeyHash {
  std::size_t operator()(const JobKey& j) const {
    return render::BrickKeyHash()(j.key) * 31 + std::size_t(j.channel);
  }
};
struct Ready {
  JobKey job;
  render::BorderedBrick brick;
  render::CellGrid cells;
  std::string bad;  // non-empty: corrupt stored data, brick is zeros
};
}  // namespace

struct BrickCache::Impl {
  const render::VolumeSource& source;
  std::int64_t budget;
  render::BorderedBrickReader reader;
  Texture zero[render::kChannelCount];

  struct Entry {
    Brick brick;
    Texture textures[render::kChannelCount];
    std::int64_t bytes = 0;
    std::uint64_t last_used = 0;
  };
  std::unordered_map<BrickKey, Entry, render::BrickKeyHash> entries;
  std::uint64_t frame = 1;
  std::unordered_set<BrickKey, render::BrickKeyHash> pinned;  // drawn by the current frame
  std::unordered_set<BrickKey, render::BrickKeyHash> wanted;  // asked for by the last request
  std::uint64_t tick = 0;  // LRU clock: uploads and use() stamp entries
  BrickCacheStats stats;

  // Worker side (guarded by mutex).
  std::mutex mutex;
  std::condition_variable work_cv, ready_cv, space_cv;
  std::deque<JobKey> queue;
  std::unordered_set<JobKey, JobKeyHash> in_flight;  // queued, decoding or ready
  std::deque<Ready> ready;
  std::size_t capacity = 4;
  bool stop = false;
  std::exception_ptr error;
  std::vector<std::thread> workers;

  Impl(const render::VolumeSource& s, std::int64_t b)
      : source(s), budget(b), reader(s, kBorder, std::max<std::int64_t>(b / 2, 64 << 20)) {}

  void work() {
    for (;;) {
      JobKey job;
      {
        std::unique_lock<std::mutex> lock(mutex);
        work_cv.wait(lock, [&] { return stop || !queue.empty(); });
        if (stop) return;
        job = queue.front();
        queue.pop_front();
      }
      Ready item{job, {}, {}, {}};
      try {
        try {
          item.brick = reader.read(job.channel, job.key);
        } catch (const FormatError& e) {  // a corrupt brick: shown as missing, not garbage
          item.bad = e.what();
          render::Region r = render::brick_region(source, job.key.level, job.key.brick);
          for (int a = 0; a < 3; ++a) {
            item.brick.offset[a] = r.offset[a] - kBorder;
            item.brick.dims[a] = r.size[a] + 2 * kBorder;
          }
          item.brick.data.assign(
              std::size_t(item.brick.dims[0] * item.brick.dims[1] * item.brick.dims[2] *
                          render::channel_bytes(job.channel)),
              0);
        }
        {
          std::array<std::int64_t, 3> size;
          for (int a = 0; a < 3; ++a)
            size[a] = item.brick.dims[a] - 2 * kBorder;
          item.cells.cell = render::cell_edge(source.brick_edge());
          render::accumulate_cells(item.cells, job.channel, item.brick.data.data(), size, kBorder);
        }
        if (job.channel == Channel::kRgba)
          render::premultiply_rgba8(item.brick.data.data(), item.brick.data.data(),
                                    std::int64_t(item.brick.data.size() / 4));
      } catch (...) {
        std::lock_guard<std::mutex> lock(mutex);
        if (!error) error = std::current_exception();
        in_flight.erase(job);
        ready_cv.notify_all();
        continue;
      }
      std::unique_lock<std::mutex> lock(mutex);
      space_cv.wait(lock, [&] { return stop || ready.size() < capacity; });
      if (stop) return;
      ready.push_back(std::move(item));
      lock.unlock();
      ready_cv.notify_one();
    }
  }

  // Evicts least recently used bricks until `need` more bytes fit: first those neither drawn
  // by the current frame nor asked for by the last request, then asked-for ones; never the
  // drawn ones (the budget is exceeded instead).
  void evict_for(std::int64_t need) {
    while (stats.resident_bytes + need > budget) {
      auto victim = entries.end();
      bool victim_wanted = true;
      for (auto it = entries.begin(); it != entries.end(); ++it) {
        if (pinned.count(it->first)) continue;
        const bool w = wanted.count(it->first) > 0;
        if (victim == entries.end() || (victim_wanted && !w) ||
            (w == victim_wanted && it->second.last_used < victim->second.last_used)) {
          victim = it;
          victim_wanted = w;
        }
      }
      if (victim == entries.end()) return;
      stats.resident_bytes -= victim->second.bytes;
      stats.resident_bricks -= 1;
      stats.evicted += 1;
      entries.erase(victim);
    }
  }

  void upload(Ready& item) {
    const std::int64_t bytes = std::int64_t(item.brick.data.size());
    evict_for(bytes);
    Entry& e = entries[item.job.key];
    if (e.bytes == 0) stats.resident_bricks += 1;
    e.last_used = ++tick;
    e.brick.offset = item.brick.offset;
    e.brick.dims = item.brick.dims;
    render::CellGrid& g = e.brick.cells;
    if (g.ranges.empty()) {
      g = std::move(item.cells);
    } else if (g.ranges.size() == item.cells.ranges.size()) {
      for (std::size_t i = 0; i < g.ranges.size(); ++i) {
        const render::ValueRange& r = item.cells.ranges[i];
        if (item.job.channel == Channel::kRgba) g.ranges[i].alpha_max = r.alpha_max;
        if (item.job.channel == Channel::kCt) {
          g.ranges[i].ct_min = r.ct_min;
          g.ranges[i].ct_max = r.ct_max;
        }
        if (item.job.channel == Channel::kLabels) g.ranges[i].labels = r.labels;
      }
      g.channels |= item.cells.channels;
    }
    const int c = int(item.job.channel);
    if (e.textures[c]) {  // replaced (should not happen): account the old bytes out
      e.bytes -= bytes;
      stats.resident_bytes -= bytes;
    }
    e.textures[c] =
        detail::allocate_texture(item.job.channel, item.brick.dims, item.brick.data.data());
    e.brick.texture[c] = e.textures[c].id();
    e.bytes += bytes;
    stats.resident_bytes += bytes;
    stats.uploaded_bricks += 1;
    stats.uploaded_bytes += bytes;
    if (!item.bad.empty()) {
      stats.bad_bricks += 1;
      stats.bad_brick_errors.push_back(std::move(item.bad));
    }
  }
};

BrickCache::BrickCache(const render::VolumeSource& source, std::int64_t budget_bytes, int threads)
    : impl_(std::make_unique<Impl>(source, budget_bytes)) {
  const std::uint8_t zeros[8] = {0};
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
    impl_->zero[int(c)] = detail::allocate_texture(c, {1, 1, 1}, zeros);
  int n = std::max(1, resolve_threads(threads));
  impl_->capacity = std::size_t(2 * n);
  for (int i = 0; i < n; ++i)
    impl_->workers.emplace_back([s = impl_.get()] { s->work(); });
}

BrickCache::~BrickCache() {
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    impl_->stop = true;
  }
  impl_->work_cv.notify_all();
  impl_->space_cv.notify_all();
  for (std::thread& t : impl_->workers)
    t.join();
}

void BrickCache::request(const std::vector<BrickKey>& keys, unsigned channels) {
  Impl& s = *impl_;
  std::lock_guard<std::mutex> lock(s.mutex);
  for (const JobKey& j : s.queue)  // dropped from the queue: no longer in flight
    s.in_flight.erase(j);
  s.queue.clear();
  s.wanted.clear();
  s.wanted.insert(keys.begin(), keys.end());
  for (const BrickKey& k : keys)
    for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels}) {
      if (!(channels & render::channel_bit(c)) || !s.source.has_channel(c)) continue;
      auto it = s.entries.find(k);
      if (it != s.entries.end() && it->second.textures[int(c)]) continue;
      JobKey j{k, c};
      if (s.in_flight.count(j)) continue;
      s.in_flight.insert(j);
      s.queue.push_back(j);
    }
  s.work_cv.notify_all();
}

int BrickCache::pump(double budget_seconds) {
  Impl& s = *impl_;
  auto t0 = std::chrono::steady_clock::now();
  int uploaded = 0;
  for (;;) {
    Ready item;
    {
      std::unique_lock<std::mutex> lock(s.mutex);
      if (budget_seconds < 0) {
        s.ready_cv.wait(lock, [&] { return !s.ready.empty() || s.in_flight.empty() || s.error; });
      }
      if (s.error) {
        std::exception_ptr e = s.error;
        s.error = nullptr;
        std::rethrow_exception(e);
      }
      if (s.ready.empty()) return uploaded;
      item = std::move(s.ready.front());
      s.ready.pop_front();
    }
    s.space_cv.notify_one();
    s.upload(item);
    ++uploaded;
    {
      std::lock_guard<std::mutex> lock(s.mutex);
      s.in_flight.erase(item.job);
    }
    if (budget_seconds >= 0 &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() >
            budget_seconds)
      return uploaded;
  }
}

bool BrickCache::busy() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return !impl_->in_flight.empty();
}

bool BrickCache::resident(const BrickKey& key, unsigned channels) const {
  auto it = impl_->entries.find(key);
  if (it == impl_->entries.end()) return false;
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
    if ((channels & render::channel_bit(c)) && impl_->source.has_channel(c) &&
        !it->second.textures[int(c)])
      return false;
  return true;
}

void BrickCache::use(const std::vector<BrickKey>& keys) {
  Impl& s = *impl_;
  s.frame += 1;
  s.pinned.clear();
  for (const BrickKey& k : keys) {
    s.pinned.insert(k);
    auto it = s.entries.find(k);
    if (it != s.entries.end()) it->second.last_used = ++s.tick;
  }
}

const BrickCache::Brick* BrickCache::find(const BrickKey& key) const {
  auto it = impl_->entries.find(key);
  return it == impl_->entries.end() ? nullptr : &it->second.brick;
}

GLuint BrickCache::zero_texture(Channel c) const {
  return impl_->zero[int(c)].id();
}

const BrickCacheStats& BrickCache::stats() const {
  impl_->stats.decoded = impl_->reader.decoded();
  return impl_->stats;
}

void BrickCache::reset_counters() {
  impl_->stats.uploaded_bricks = 0;
  impl_->stats.uploaded_bytes = 0;
}

std::int64_t BrickCache::budget_bytes() const {
  return impl_->budget;
}

}  // namespace vispack::viewer

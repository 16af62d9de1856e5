#include "vispack/viewer/volume_textures.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <exception>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "texture_format.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/render/reference.h"

namespace vispack::viewer {

using render::Channel;

std::int64_t level_texture_bytes(const render::VolumeSource& source, int level) {
  std::int64_t voxels = source.level(level).voxels();
  std::int64_t bytes = 0;
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
    if (source.has_channel(c)) bytes += voxels * render::channel_bytes(c);
  return bytes;
}

int choose_level(const render::VolumeSource& source, int max_texture_size, std::int64_t max_bytes) {
  int levels = source.level_count();
  for (int l = 0; l < levels; ++l) {
    render::LevelGeometry g = source.level(l);
    bool fits = g.dims[0] <= max_texture_size && g.dims[1] <= max_texture_size &&
                g.dims[2] <= max_texture_size && level_texture_bytes(source, l) <= max_bytes;
    if (fits) return l;
  }
  return levels - 1;
}

namespace {

using detail::format_of;
using Format = detail::TextureFormat;
Texture allocate(Channel c, const std::array<std::int64_t, 3>& dims) {
  return detail::allocate_texture(c, dims);
}

struct Job {
  Channel channel;
  render::Region region;
};
struct Item {
  Job job;
  std::vector<std::uint8_t> data;
  std::string bad;  // non-empty: the region's stored data is corrupt (data is all zeros)
};

}  // namespace

struct VolumeTextures::Impl {
  const render::VolumeSource* source = nullptr;
  int level = 0;
  render::LevelGeometry geometry;
  Texture textures[render::kChannelCount];
  bool present[render::kChannelCount] = {false, false, false};
  std::vector<Job> jobs;
  std::atomic<std::size_t> next{0};
  std::mutex mutex;
  std::condition_variable ready_cv, space_cv;
  std::deque<Item> ready;
  std::size_t capacity = 4;
  int active = 0;
  bool stop = false;
  std::exception_ptr error;
  std::vector<std::thread> workers;
  UploadStats stats;
  std::chrono::steady_clock::time_point start;
  bool complete = true;

  void join() {
    {
      std::lock_guard<std::mutex> lock(mutex);
      stop = true;
    }
    space_cv.notify_all();
    for (std::thread& t : workers)
      if (t.joinable()) t.join();
    workers.clear();
  }
  ~Impl() { join(); }

  void work() {
    try {
      for (;;) {
        {
          std::lock_guard<std::mutex> lock(mutex);
          if (stop) break;
        }
        std::size_t i = next.fetch_add(1);
        if (i >= jobs.size()) break;
        Item item{jobs[i], {}, {}};
        int bpv = render::channel_bytes(item.job.channel);
        item.data.resize(std::size_t(item.job.region.voxels()) * std::size_t(bpv));
        try {
          source->read_region(item.job.channel, level, item.job.region, item.data.data());
        } catch (const FormatError& e) {  // a corrupt brick: shown as missing, not garbage
          std::fill(item.data.begin(), item.data.end(), std::uint8_t(0));
          item.bad = e.what();
        }
        if (item.job.channel == Channel::kRgba)
          render::premultiply_rgba8(item.data.data(), item.data.data(), item.job.region.voxels());
        std::unique_lock<std::mutex> lock(mutex);
        space_cv.wait(lock, [&] { return stop || ready.size() < capacity; });
        if (stop) break;
        ready.push_back(std::move(item));
        lock.unlock();
        ready_cv.notify_one();
      }
    } catch (...) {
      std::lock_guard<std::mutex> lock(mutex);
      if (!error) error = std::current_exception();
      stop = true;
    }
    {
      std::lock_guard<std::mutex> lock(mutex);
      --active;
    }
    ready_cv.notify_all();
    space_cv.notify_all();
  }
};

VolumeTextures::VolumeTextures() : impl_(std::make_unique<Impl>()) {
  impl_->geometry.dims = {1, 1, 1};
  const std::uint8_t zeros[8] = {0};
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels}) {
    impl_->textures[int(c)] = allocate(c, {1, 1, 1});
    Format f = format_of(c);
    glTexSubImage3D(GL_TEXTURE_3D, 0, 0, 0, 0, 1, 1, 1, f.format, f.type, zeros);
  }
  check_gl("creating empty volume textures");
}
VolumeTextures::~VolumeTextures() = default;
VolumeTextures::VolumeTextures(VolumeTextures&&) noexcept = default;
VolumeTextures& VolumeTextures::operator=(VolumeTextures&&) noexcept = default;

void VolumeTextures::begin(const render::VolumeSource& source, int level, int threads) {
  Impl& s = *impl_;
  s.join();
  s.ready.clear();
  s.error = nullptr;
  s.stop = false;
  s.source = &source;
  s.level = level;
  s.geometry = source.level(level);
  s.stats = {};
  s.start = std::chrono::steady_clock::now();
  s.jobs.clear();
  s.next = 0;
  int edge = std::max(1, source.brick_edge());
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels}) {
    s.present[int(c)] = source.has_channel(c);
    if (!source.has_channel(c)) {
      const std::uint8_t zeros[8] = {0};
      Format f = format_of(c);
      s.textures[int(c)] = allocate(c, {1, 1, 1});
      glTexSubImage3D(GL_TEXTURE_3D, 0, 0, 0, 0, 1, 1, 1, f.format, f.type, zeros);
      continue;
    }
    s.textures[int(c)] = allocate(c, s.geometry.dims);
    for (std::int64_t z = 0; z < s.geometry.dims[2]; z += edge)
      for (std::int64_t y = 0; y < s.geometry.dims[1]; y += edge)
        for (std::int64_t x = 0; x < s.geometry.dims[0]; x += edge) {
          render::Region r;
          r.offset = {x, y, z};
          r.size = {std::min<std::int64_t>(edge, s.geometry.dims[0] - x),
                    std::min<std::int64_t>(edge, s.geometry.dims[1] - y),
                    std::min<std::int64_t>(edge, s.geometry.dims[2] - z)};
          s.jobs.push_back({c, r});
        }
  }
  int n = std::max(1, resolve_threads(threads));
  s.capacity = std::size_t(2 * n);
  s.complete = false;
  s.active = n;
  for (int i = 0; i < n; ++i)
    s.workers.emplace_back([&s] { s.work(); });
}

bool VolumeTextures::pump(double budget_seconds) {
  Impl& s = *impl_;
  if (s.complete) return true;
  auto t0 = std::chrono::steady_clock::now();
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  for (;;) {
    Item item;
    {
      std::unique_lock<std::mutex> lock(s.mutex);
      s.ready_cv.wait(lock, [&] { return !s.ready.empty() || s.active == 0 || s.error; });
      if (s.error) {
        std::exception_ptr e = s.error;
        lock.unlock();
        s.join();
        s.complete = true;  // nothing more will come
        std::rethrow_exception(e);
      }
      if (s.ready.empty()) {
        lock.unlock();
        s.join();
        s.complete = true;
        s.stats.seconds =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - s.start).count();
        return true;
      }
      item = std::move(s.ready.front());
      s.ready.pop_front();
    }
    s.space_cv.notify_one();
    Format f = format_of(item.job.channel);
    const render::Region& r = item.job.region;
    glBindTexture(GL_TEXTURE_3D, s.textures[int(item.job.channel)].id());
    glTexSubImage3D(GL_TEXTURE_3D, 0, GLint(r.offset[0]), GLint(r.offset[1]), GLint(r.offset[2]),
                    GLsizei(r.size[0]), GLsizei(r.size[1]), GLsizei(r.size[2]), f.format, f.type,
                    item.data.data());
    s.stats.bricks += 1;
    s.stats.bytes += std::int64_t(item.data.size());
    if (!item.bad.empty()) {
      s.stats.bad_bricks += 1;
      s.stats.bad_brick_errors.push_back(std::move(item.bad));
    }
    if (budget_seconds >= 0 &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() >
            budget_seconds) {
      check_gl("uploading bricks");
      return false;
    }
  }
}

UploadStats VolumeTextures::upload(const render::VolumeSource& source, int level, int threads) {
  begin(source, level, threads);
  pump(-1.0);
  glFinish();
  check_gl("uploading a level");
  impl_->stats.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - impl_->start).count();
  return impl_->stats;
}

bool VolumeTextures::complete() const {
  return impl_->complete;
}
const UploadStats& VolumeTextures::stats() const {
  return impl_->stats;
}
const render::LevelGeometry& VolumeTextures::geometry() const {
  return impl_->geometry;
}
int VolumeTextures::level() const {
  return impl_->level;
}
GLuint VolumeTextures::texture(Channel c) const {
  return impl_->textures[int(c)].id();
}
bool VolumeTextures::has(Channel c) const {
  return impl_->present[int(c)];
}

}  // namespace vispack::viewer

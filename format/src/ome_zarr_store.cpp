#include "ome_zarr_store.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <limits>

#include "vispack/common/error.h"

namespace vispack::format::ome_zarr {
namespace {

namespace fs = std::filesystem;

void write_all(int fd, const void* data, std::size_t size, const std::string& what) {
  const auto* p = static_cast<const std::uint8_t*>(data);
  while (size > 0) {
    const ssize_t n = ::write(fd, p, size);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) throw IoError(cat(what, ": cannot write: ", std::strerror(errno)));
    p += n;
    size -= std::size_t(n);
  }
}

void sync_folder(const std::string& path, bool whole_file_system) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) throw IoError(cat(path, ": cannot open the folder: ", std::strerror(errno)));
  const int r = whole_file_system ? ::syncfs(fd) : ::fsync(fd);
  const int err = errno;
  ::close(fd);
  if (r != 0) throw IoError(cat(path, ": cannot sync: ", std::strerror(err)));
}

std::string trimmed(std::string path) {
  while (path.size() > 1 && path.back() == '/')
    path.pop_back();
  return path;
}

std::string brick_key(const std::array<std::int64_t, 3>& b) {
  return cat(b[2], "/", b[1], "/", b[0]);
}

constexpr std::uint64_t kAbsent = std::numeric_limits<std::uint64_t>::max();

}  // namespace

std::uint32_t crc32c(const void* data, std::size_t size, std::uint32_t crc) {
  static const auto table = [] {
    std::array<std::uint32_t, 256> t{};
    for (std::uint32_t i = 0; i < 256; ++i) {
      std::uint32_t c = i;
      for (int k = 0; k < 8; ++k)
        c = (c & 1) ? (c >> 1) ^ 0x82F63B78u : c >> 1;
      t[i] = c;
    }
    return t;
  }();
  const auto* p = static_cast<const std::uint8_t*>(data);
  crc = ~crc;
  for (std::size_t i = 0; i < size; ++i)
    crc = table[(crc ^ p[i]) & 0xFF] ^ (crc >> 8);
  return ~crc;
}

OutputFolder::OutputFolder(std::string final_path, bool overwrite)
    : final_(trimmed(std::move(final_path))), overwrite_(overwrite) {
  if (final_.empty()) throw UsageError("the output folder name is empty");
  std::error_code ec;
  if (fs::exists(final_, ec) && !overwrite_)
    throw UsageError(cat(final_, ": exists (remove it, or pass --overwrite)"));
  const fs::path parent = fs::path(final_).parent_path();
  if (!parent.empty() && !fs::is_directory(parent, ec))
    throw IoError(cat(final_, ": its folder ", parent.string(), " does not exist"));
  std::string name = final_ + ".partial-XXXXXX";
  if (::mkdtemp(name.data()) == nullptr)
    throw IoError(cat(name, ": cannot create the output folder: ", std::strerror(errno)));
  root_ = name;
  folders_.insert("");
}

OutputFolder::~OutputFolder() {
  if (!committed_) {
    std::error_code ec;
    fs::remove_all(root_, ec);
  }
}

void OutputFolder::make_folder(const std::string& relative) {
  if (folders_.count(relative)) return;
  const auto slash = relative.rfind('/');
  make_folder(slash == std::string::npos ? std::string() : relative.substr(0, slash));
  const std::string path = root_ + "/" + relative;
  if (::mkdir(path.c_str(), 0755) != 0 && errno != EEXIST)
    throw IoError(cat(final_, "/", relative, ": cannot create: ", std::strerror(errno)));
  folders_.insert(relative);
}

void OutputFolder::write_file(const std::string& relative, const void* data, std::size_t size) {
  const auto slash = relative.rfind('/');
  if (slash != std::string::npos) make_folder(relative.substr(0, slash));
  const std::string path = root_ + "/" + relative;
  const std::string what = cat(final_, "/", relative);
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) throw IoError(cat(what, ": cannot create: ", std::strerror(errno)));
  try {
    write_all(fd, data, size, what);
  } catch (...) {
    ::close(fd);
    throw;
  }
  if (::close(fd) != 0) throw IoError(cat(what, ": cannot close: ", std::strerror(errno)));
  count(1, size);
}

void OutputFolder::write_json(const std::string& relative, const nlohmann::json& doc) {
  const std::string text = doc.dump(2) + "\n";
  write_file(relative, text.data(), text.size());
}

void OutputFolder::commit() {
  sync_folder(root_, true);
  std::error_code ec;
  std::string aside;
  if (fs::exists(final_, ec)) {
    if (!overwrite_) throw UsageError(cat(final_, ": exists (remove it, or pass --overwrite)"));
    aside = root_ + ".old";
    if (::rename(final_.c_str(), aside.c_str()) != 0)
      throw IoError(cat(final_, ": cannot move aside: ", std::strerror(errno)));
  }
  if (::rename(root_.c_str(), final_.c_str()) != 0)
    throw IoError(cat(root_, ": cannot rename to ", final_, ": ", std::strerror(errno)));
  committed_ = true;
  const fs::path parent = fs::path(final_).parent_path();
  sync_folder(parent.empty() ? "." : parent.string(), false);
  root_ = final_;
  if (!aside.empty()) fs::remove_all(aside, ec);
}

V2ChunkWriter::V2ChunkWriter(OutputFolder& folder, std::string array, bool channel_axis)
    : folder_(folder), prefix_(std::move(array) + (channel_axis ? "/0/" : "/")) {}

void V2ChunkWriter::put(const std::array<std::int64_t, 3>& brick, const void* data,
                        std::size_t size) {
  if (size == 0) return;
  folder_.write_file(prefix_ + brick_key(brick), data, size);
}

ShardWriter::ShardWriter(OutputFolder& folder, std::string array, bool channel_axis,
                         int shard_bricks)
    : folder_(folder),
      prefix_(std::move(array) + (channel_axis ? "/c/0/" : "/c/")),
      s_(shard_bricks) {}

ShardWriter::~ShardWriter() {
  if (fd_ >= 0) ::close(fd_);
}

void ShardWriter::put(const std::array<std::int64_t, 3>& brick, const void* data,
                      std::size_t size) {
  const std::array<std::int64_t, 3> shard{brick[0] / s_, brick[1] / s_, brick[2] / s_};
  if (shard != shard_) {
    close_shard();
    shard_ = shard;
    index_.assign(std::size_t(2 * s_ * s_ * s_), kAbsent);
  }
  if (size == 0) return;
  if (fd_ < 0) {
    const std::string relative = prefix_ + brick_key(shard);
    folder_.make_folder(relative.substr(0, relative.rfind('/')));
    path_ = cat(folder_.final_path(), "/", relative);
    const std::string real = folder_.root() + "/" + relative;
    fd_ = ::open(real.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (fd_ < 0) throw IoError(cat(path_, ": cannot create: ", std::strerror(errno)));
    offset_ = 0;
  }
  write_all(fd_, data, size, path_);
  const std::size_t inner =
      std::size_t(((brick[2] % s_) * s_ + brick[1] % s_) * s_ + brick[0] % s_);
  index_[2 * inner] = offset_;
  index_[2 * inner + 1] = size;
  offset_ += size;
}

void ShardWriter::close_shard() {
  if (fd_ < 0) return;
  // The index as little-endian u64 (the machines vispack builds on are little-endian, as the
  // packed format itself assumes), then its crc32c.
  const std::size_t index_bytes = index_.size() * sizeof(std::uint64_t);
  const std::uint32_t crc = crc32c(index_.data(), index_bytes);
  write_all(fd_, index_.data(), index_bytes, path_);
  write_all(fd_, &crc, sizeof crc, path_);
  const int fd = fd_;
  fd_ = -1;
  if (::close(fd) != 0) throw IoError(cat(path_, ": cannot close: ", std::strerror(errno)));
  folder_.count(1, offset_ + index_bytes + sizeof crc);
  ++shards_;
}

void ShardWriter::finish() {
  close_shard();
}

std::vector<std::array<std::int64_t, 3>> chunk_order(const std::array<std::int64_t, 3>& grid,
                                                     int shard_bricks) {
  std::vector<std::array<std::int64_t, 3>> order;
  order.reserve(std::size_t(grid[0] * grid[1] * grid[2]));
  const std::int64_t s = shard_bricks > 0 ? shard_bricks : std::max({grid[0], grid[1], grid[2]});
  for (std::int64_t sz = 0; sz < grid[2]; sz += s)
    for (std::int64_t sy = 0; sy < grid[1]; sy += s)
      for (std::int64_t sx = 0; sx < grid[0]; sx += s)
        for (std::int64_t bz = sz; bz < std::min(sz + s, grid[2]); ++bz)
          for (std::int64_t by = sy; by < std::min(sy + s, grid[1]); ++by)
            for (std::int64_t bx = sx; bx < std::min(sx + s, grid[0]); ++bx)
              order.push_back({bx, by, bz});
  return order;
}

}  // namespace vispack::format::ome_zarr

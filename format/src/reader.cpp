#include "vispack/format/reader.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>
#include <xxhash.h>
#include <zstd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <limits>
#include <mutex>
#include <stdexcept>

#include "layout.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"
#include "vispack/format/metadata.h"

#include "reader_impl.h"

namespace vispack::format {

using namespace detail;

Reader::Reader(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Reader::~Reader() = default;
Reader::Reader(Reader&&) noexcept = default;
Reader& Reader::operator=(Reader&&) noexcept = default;

Reader Reader::open(const std::string& path, const ReaderLimits& limits) {
  auto impl = std::make_unique<Impl>();
  impl->path = path;
  impl->map();
  impl->parse_header(limits);
  impl->parse_metadata(limits);
  impl->parse_index();
  return Reader(std::move(impl));
}

const std::string& Reader::path() const {
  return impl_->path;
}
std::uint64_t Reader::file_size() const {
  return impl_->size;
}
std::uint16_t Reader::version_major() const {
  return impl_->header.version_major;
}
std::uint16_t Reader::version_minor() const {
  return impl_->header.version_minor;
}
const nlohmann::json& Reader::metadata() const {
  return impl_->meta;
}
int Reader::brick_edge() const {
  return impl_->edge;
}
int Reader::level_count() const {
  return int(impl_->levels.size());
}
const LevelInfo& Reader::level(int level) const {
  if (level < 0 || level >= level_count()) {
    throw std::out_of_range(
        cat(impl_->path, ": level ", level, " outside [0, ", level_count(), ")"));
  }
  return impl_->levels[std::size_t(level)];
}
const std::vector<ChannelSpec>& Reader::channels() const {
  return impl_->channels;
}
std::optional<int> Reader::find_channel(const std::string& name) const {
  for (std::size_t i = 0; i < impl_->channels.size(); ++i) {
    if (impl_->channels[i].name == name) return int(i);
  }
  return std::nullopt;
}
int Reader::channel_index(const std::string& name) const {
  auto c = find_channel(name);
  if (!c) throw std::out_of_range(cat(impl_->path, ": no channel \"", name, "\""));
  return *c;
}
const std::vector<LabelEntry>& Reader::label_table() const {
  return impl_->label_table;
}
std::size_t Reader::brick_bytes(int channel) const {
  if (channel < 0 || channel >= int(impl_->channels.size())) {
    throw std::out_of_range(cat(impl_->path, ": channel ", channel, " out of range"));
  }
  return impl_->brick_bytes(channel);
}
const BrickInfo& Reader::brick(int channel, int level, std::int64_t bx, std::int64_t by,
                               std::int64_t bz) const {
  return impl_->brick(channel, level, bx, by, bz);
}
const std::vector<BrickInfo>& Reader::bricks() const {
  return impl_->bricks;
}
const std::vector<std::uint32_t>& Reader::label_ids() const {
  return impl_->label_ids;
}
std::vector<std::uint32_t> Reader::brick_labels(const BrickInfo& b) const {
  const auto& ids = impl_->label_ids;
  if (std::uint64_t(b.label_first) + b.label_count > ids.size()) {
    throw std::out_of_range(cat(impl_->path, ": label range outside the file's label IDs"));
  }
  return std::vector<std::uint32_t>(ids.begin() + b.label_first,
                                    ids.begin() + b.label_first + b.label_count);
}
std::optional<ByteView> Reader::raw_brick_view(const BrickInfo& b) const {
  if (b.codec != Codec::kRaw) return std::nullopt;
  return payload(b);
}
ByteView Reader::payload(const BrickInfo& b) const {
  if (b.codec == Codec::kUniform) return {};
  if (b.offset < kPayloadAlignment || b.offset + b.stored_size > impl_->header.payload_end) {
    throw std::out_of_range(cat(impl_->path, ": BrickInfo not from this file"));
  }
  return {impl_->base + b.offset, std::size_t(b.stored_size)};
}
void Reader::release_payload_pages(const BrickInfo& b) const {
  const ByteView view = payload(b);
  if (view.size == 0) return;
  // A payload starts on a page and is zero-padded to the next one (SPEC.md "File layout"), so
  // its pages hold no other payload. Advice only: a failure changes nothing but the memory use.
  const std::size_t length = std::size_t(align_up(b.stored_size, kPayloadAlignment));
  ::madvise(const_cast<std::uint8_t*>(view.data), length, MADV_DONTNEED);
}
void Reader::decode_brick(const BrickInfo& b, void* out, std::size_t out_size,
                          bool verify_checksum) const {
  const BrickInfo& own = brick(b.channel, b.level, b.brick[0], b.brick[1], b.brick[2]);
  impl_->decode(own, out, out_size, verify_checksum);
}
void Reader::read_region(int channel, int level, std::int64_t x0, std::int64_t y0, std::int64_t z0,
                         std::int64_t nx, std::int64_t ny, std::int64_t nz, void* out) const {
  impl_->region(channel, level, {x0, y0, z0}, {nx, ny, nz}, out, 1);
}
std::vector<std::uint8_t> Reader::read_level(int channel, int level, int threads) const {
  const LevelInfo& li = this->level(level);
  if (channel < 0 || channel >= int(impl_->channels.size())) {
    throw std::out_of_range(cat(impl_->path, ": channel ", channel, " out of range"));
  }
  std::vector<std::uint8_t> out(std::size_t(li.dims[0]) * std::size_t(li.dims[1]) *
                                std::size_t(li.dims[2]) *
                                channel_type_bytes(impl_->channels[std::size_t(channel)].type));
  impl_->region(channel, level, {0, 0, 0}, li.dims, out.data(), resolve_threads(threads));
  return out;
}

}  // namespace vispack::format

// Reader::check and Reader::verify: every brick against its index entry, and the padding
// (reader_impl.h).
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
using nlohmann::json;

namespace {

// "v0,v1,..." of the first `n` values.
template <typename Values>
std::string comma_list(const Values& v, std::size_t n) {
  std::string t;
  for (std::size_t k = 0; k < n; ++k)
    t += cat(k ? "," : "", v[k]);
  return t;
}

}  // namespace

// Reader::check's look at one brick: its payload checksum, and with `deep` its decoded voxels'
// min/max and (labels) ID set against the index. The brick's first problem, if any.
std::optional<Finding> Reader::Impl::check_brick(const BrickInfo& b, bool deep) const {
  if (b.codec != Codec::kUniform) {
    std::uint64_t sum = xxh64(base + b.offset, std::size_t(b.stored_size));
    if (sum != b.checksum) {
      return finding(DefectKind::kPayloadChecksum, b.level, b.channel, b.brick,
                     cat("payload checksum mismatch (stored ", hex64(b.checksum), ", computed ",
                         hex64(sum), ")"));
    }
  }
  if (!deep) return std::nullopt;
  std::vector<std::uint8_t> buf(brick_bytes(b.channel));
  try {
    decode(b, buf.data(), buf.size(), false);
  } catch (const FileDefect& e) {
    return e.finding();
  }
  return check_decoded(b, buf);
}

// The decoded voxels `buf` of brick b against its index entry: min/max per component, and for
// a label channel the set of IDs present.
std::optional<Finding> Reader::Impl::check_decoded(const BrickInfo& b,
                                                   const std::vector<std::uint8_t>& buf) const {
  const ChannelType type = channels[std::size_t(b.channel)].type;
  const std::size_t vb = channel_type_bytes(type);
  std::array<std::int64_t, 4> lo{}, hi{};
  lo.fill(std::numeric_limits<std::int64_t>::max());
  hi.fill(std::numeric_limits<std::int64_t>::min());
  std::vector<bool> seen(is_label_type(type) ? 65536 : 0);
  for (std::size_t v = 0; v < buf.size(); v += vb) {
    auto val = decode_value(type, buf.data() + v);
    for (int c = 0; c < channel_type_components(type); ++c) {
      lo[c] = std::min(lo[c], val[c]);
      hi[c] = std::max(hi[c], val[c]);
    }
    if (!seen.empty()) seen[std::size_t(val[0])] = true;
  }
  const std::size_t comps = std::size_t(channel_type_components(type));
  for (std::size_t c = 0; c < comps; ++c) {
    if (lo[c] != b.min[c] || hi[c] != b.max[c]) {
      return finding(DefectKind::kBrickRange, b.level, b.channel, b.brick,
                     cat("decoded min/max (", comma_list(lo, comps), ")..(", comma_list(hi, comps),
                         ") differ from the index (", comma_list(b.min, comps), ")..(",
                         comma_list(b.max, comps), ")"));
    }
  }
  if (seen.empty()) return std::nullopt;
  std::vector<std::uint32_t> ids;
  for (std::uint32_t id = 0; id < 65536; ++id)
    if (seen[id]) ids.push_back(id);
  const std::vector<std::uint32_t> index_ids(label_ids.begin() + b.label_first,
                                             label_ids.begin() + b.label_first + b.label_count);
  if (ids == index_ids) return std::nullopt;
  return finding(DefectKind::kBrickLabels, b.level, b.channel, b.brick,
                 cat("decoded label set {", comma_list(ids, ids.size()),
                     "} differs from the index {", comma_list(index_ids, index_ids.size()), "}"));
}

// Padding: every byte outside the header, payloads, metadata, index and label IDs is zero. One
// finding per padding run with a non-zero byte, in file order, appended to `findings`.
void Reader::Impl::check_padding(std::vector<Finding>& findings) const {
  auto check_zero = [&](std::uint64_t from, std::uint64_t to, const BrickInfo* after) {
    for (std::uint64_t p = from; p < to; ++p) {
      if (base[p] != 0) {
        Finding f;
        if (after) {
          f = finding(DefectKind::kPadding, after->level, after->channel, after->brick,
                      cat("non-zero padding byte at offset ", p, " after the payload"));
        } else {
          f.kind = DefectKind::kPadding;
          f.detail = cat("non-zero padding byte at offset ", p);
        }
        findings.push_back(std::move(f));
        return;
      }
    }
  };
  check_zero(detail::kHeaderSize, header.payload_offset, nullptr);
  std::vector<const BrickInfo*> stored;
  for (const BrickInfo& b : bricks)
    if (b.codec != Codec::kUniform) stored.push_back(&b);
  std::sort(stored.begin(), stored.end(),
            [](const BrickInfo* a, const BrickInfo* b) { return a->offset < b->offset; });
  for (std::size_t i = 0; i < stored.size(); ++i) {
    std::uint64_t end = stored[i]->offset + stored[i]->stored_size;
    std::uint64_t next = i + 1 < stored.size() ? stored[i + 1]->offset : header.payload_end;
    check_zero(end, next, stored[i]);
  }
  check_zero(header.metadata_offset + header.metadata_size, header.index_offset, nullptr);
}

std::vector<Finding> Reader::check(bool deep, int threads) const {
  const Impl& m = *impl_;
  // At most one finding per brick (its first problem), sorted into index order at the end.
  std::mutex found_mutex;
  std::vector<std::pair<std::size_t, Finding>> per_brick;
  parallel_for(std::int64_t(m.bricks.size()), resolve_threads(threads), [&](std::int64_t i) {
    std::optional<Finding> f = m.check_brick(m.bricks[std::size_t(i)], deep);
    if (!f) return;
    std::lock_guard<std::mutex> lock(found_mutex);
    per_brick.emplace_back(std::size_t(i), std::move(*f));
  });
  std::sort(per_brick.begin(), per_brick.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  std::vector<Finding> findings;
  for (auto& f : per_brick)
    findings.push_back(std::move(f.second));
  m.check_padding(findings);
  return findings;
}

VerifyResult Reader::verify(bool deep, int threads) const {
  VerifyResult result;
  std::vector<Finding> findings = check(deep, threads);
  if (findings.empty()) return result;
  const Finding& f = findings.front();
  result.ok = false;
  result.message = cat(impl_->path, ": ", f.where(), f.detail);
  if (f.has_brick) result.brick = brick(f.channel, f.level, f.brick[0], f.brick[1], f.brick[2]);
  return result;
}

}  // namespace vispack::format

// Reader::Impl: the brick index, each entry checked before use, and the payloads' layout
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

void Reader::Impl::parse_index() {
  const FileHeader& h = header;
  label_ids.resize(std::size_t(h.labels_count));
  if (h.labels_count)
    std::memcpy(label_ids.data(), base + h.labels_offset, std::size_t(h.labels_count) * 4);
  bricks.resize(std::size_t(h.index_count));
  std::vector<PayloadSpan> spans;
  std::size_t k = 0;
  for (int l = 0; l < int(levels.size()); ++l) {
    const LevelInfo& li = levels[std::size_t(l)];
    for (int c = 0; c < int(channels.size()); ++c)
      for (std::int64_t bz = 0; bz < li.bricks[2]; ++bz)
        for (std::int64_t by = 0; by < li.bricks[1]; ++by)
          for (std::int64_t bx = 0; bx < li.bricks[0]; ++bx, ++k)
            parse_entry(k, l, c, {bx, by, bz}, spans);
  }
  check_payload_spans(spans);
}

void Reader::Impl::parse_entry(std::size_t k, int l, int c, const std::array<std::int64_t, 3>& at,
                               std::vector<PayloadSpan>& spans) {
  const ChannelType type = channels[std::size_t(c)].type;
  const std::size_t vbytes = channel_type_bytes(type);
  IndexEntry e;
  std::memcpy(&e, base + header.index_offset + k * sizeof(IndexEntry), sizeof(e));
  auto bad = [&](const std::string& what) {
    fail_brick(DefectKind::kIndexEntry, l, c, at[0], at[1], at[2], what);
  };
  if (e.level != l || e.channel != c || e.bx != at[0] || e.by != at[1] || e.bz != at[2]) {
    bad(cat("index entry ", k, " is for level ", int(e.level), " channel ", int(e.channel),
            " brick (", e.bx, ",", e.by, ",", e.bz, "), expected this brick"));
  }
  if (e.reserved != 0) bad(cat("reserved byte is not zero"));
  for (std::size_t i = vbytes; i < 8; ++i) {
    if (e.min[i] != 0 || e.max[i] != 0) bad(cat("min/max bytes past the voxel size are not zero"));
  }
  BrickInfo& b = bricks[k];
  b.level = l;
  b.channel = c;
  b.brick = at;
  b.offset = e.offset;
  b.stored_size = e.stored_size;
  b.checksum = e.checksum;
  b.min = decode_value(type, e.min);
  b.max = decode_value(type, e.max);
  std::memcpy(b.uniform.data(), e.min, 4);
  b.label_first = e.label_first;
  b.label_count = e.label_count;
  for (int comp = 0; comp < 4; ++comp) {
    if (b.min[comp] > b.max[comp]) bad(cat("min > max"));
  }
  check_entry_codec(e, b, brick_bytes(c), bad);
  if (b.codec != Codec::kUniform) spans.push_back({e.offset, e.offset + e.stored_size, k});
  check_entry_labels(e, b, type, bad);
}

template <class Bad>
void Reader::Impl::check_entry_codec(const IndexEntry& e, BrickInfo& b, std::uint64_t raw_bytes,
                                     const Bad& bad) const {
  const FileHeader& h = header;
  switch (e.codec) {
    case std::uint8_t(Codec::kUniform):
      b.codec = Codec::kUniform;
      if (e.offset || e.stored_size || e.checksum)
        bad(cat("uniform brick with a payload offset, size or checksum"));
      if (std::memcmp(e.min, e.max, 8) != 0) bad(cat("uniform brick with min != max"));
      break;
    case std::uint8_t(Codec::kRaw):
    case std::uint8_t(Codec::kZstd): {
      b.codec = Codec(e.codec);
      if (b.codec == Codec::kRaw && e.stored_size != raw_bytes)
        bad(cat("raw brick of ", e.stored_size, " bytes, expected ", raw_bytes));
      if (b.codec == Codec::kZstd && (e.stored_size == 0 || e.stored_size >= raw_bytes))
        bad(cat("zstd brick of ", e.stored_size, " bytes (must be in [1, ", raw_bytes, "))"));
      if (e.offset % kPayloadAlignment != 0)
        bad(cat("payload offset ", e.offset, " is not a multiple of 4096"));
      auto end = add(e.offset, e.stored_size);
      if (e.offset < h.payload_offset || !end || *end > h.payload_end) {
        bad(cat("payload [", e.offset, ", +", e.stored_size, ") lies outside the payload area [",
                h.payload_offset, ", ", h.payload_end, ")"));
      }
      break;
    }
    default:
      bad(cat("unknown codec ", int(e.codec)));
  }
}

template <class Bad>
void Reader::Impl::check_entry_labels(const IndexEntry& e, const BrickInfo& b, ChannelType type,
                                      const Bad& bad) const {
  if (!is_label_type(type)) {
    if (e.label_count != 0 || e.label_first != 0)
      bad(cat("label set on a channel that is not a label channel"));
    return;
  }
  if (e.label_count == 0 || std::uint64_t(e.label_first) + e.label_count > header.labels_count) {
    bad(cat("label set [", e.label_first, ", +", e.label_count, ") is empty or outside the ",
            header.labels_count, " label IDs"));
  }
  const std::uint32_t limit = type == ChannelType::kUint8 ? 255 : 65535;
  const std::uint32_t* ids = label_ids.data() + e.label_first;
  for (std::uint32_t i = 0; i < e.label_count; ++i) {
    if (ids[i] > limit || (i > 0 && ids[i] <= ids[i - 1]))
      bad(cat("label set is not strictly ascending within the type's range"));
  }
  if (ids[0] != std::uint64_t(b.min[0]) || ids[e.label_count - 1] != std::uint64_t(b.max[0])) {
    bad(cat("label set does not match min/max"));
  }
}

void Reader::Impl::check_payload_spans(std::vector<PayloadSpan>& spans) const {
  const FileHeader& h = header;
  std::sort(spans.begin(), spans.end(),
            [](const PayloadSpan& a, const PayloadSpan& b) { return a.offset < b.offset; });
  std::uint64_t cursor = h.payload_offset;
  for (const PayloadSpan& s : spans) {
    if (s.offset < cursor)
      fail_brick(DefectKind::kIndexEntry, bricks[s.k],
                 cat("payload at ", s.offset, " overlaps the previous brick (which ends at ",
                     cursor, ")"));
    cursor = align_up(s.end, kPayloadAlignment);
  }
  if (cursor != h.payload_end)
    fail(DefectKind::kIndexEntry, cat("payload_end ", h.payload_end,
                                      " is not the aligned end of the last payload ", cursor));
}

}  // namespace vispack::format

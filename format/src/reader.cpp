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

namespace vispack::format {
namespace {

using detail::align_up;
using detail::FileHeader;
using detail::IndexEntry;
using nlohmann::json;

// a * b, or nullopt when it overflows uint64.
std::optional<std::uint64_t> mul(std::uint64_t a, std::uint64_t b) {
  if (a != 0 && b > std::numeric_limits<std::uint64_t>::max() / a) return std::nullopt;
  return a * b;
}
std::optional<std::uint64_t> add(std::uint64_t a, std::uint64_t b) {
  if (b > std::numeric_limits<std::uint64_t>::max() - a) return std::nullopt;
  return a + b;
}

std::string brick_name(const std::vector<ChannelSpec>& channels, int level, int channel,
                       std::int64_t bx, std::int64_t by, std::int64_t bz) {
  std::string name =
      channel >= 0 && channel < int(channels.size()) ? channels[channel].name : cat("#", channel);
  return cat("level ", level, " channel ", name, " brick (", bx, ",", by, ",", bz, ")");
}

// Decodes the voxel bytes of a min/max field into per-component integers.
std::array<std::int64_t, 4> decode_value(ChannelType type, const std::uint8_t* bytes) {
  std::array<std::int64_t, 4> out{0, 0, 0, 0};
  switch (type) {
    case ChannelType::kRgba8:
      for (int c = 0; c < 4; ++c)
        out[c] = bytes[c];
      break;
    case ChannelType::kInt16: {
      std::int16_t v;
      std::memcpy(&v, bytes, 2);
      out[0] = v;
      break;
    }
    case ChannelType::kUint8:
      out[0] = bytes[0];
      break;
    case ChannelType::kUint16: {
      std::uint16_t v;
      std::memcpy(&v, bytes, 2);
      out[0] = v;
      break;
    }
  }
  return out;
}

}  // namespace

struct Reader::Impl {
  std::string path;
  int fd = -1;
  const std::uint8_t* base = nullptr;
  std::size_t size = 0;
  FileHeader header{};
  json meta;
  int edge = 0;
  VolumeGeometry geometry;
  const std::vector<LevelInfo>& levels = geometry.levels;
  std::vector<ChannelSpec> channels;
  std::vector<LabelEntry> label_table;
  std::vector<BrickInfo> bricks;
  std::vector<std::uint32_t> label_ids;
  mutable std::mutex dctx_mutex;
  mutable std::vector<ZSTD_DCtx*> dctx_free;

  ~Impl() {
    for (ZSTD_DCtx* d : dctx_free)
      ZSTD_freeDCtx(d);
    if (base) ::munmap(const_cast<std::uint8_t*>(base), size);
    if (fd >= 0) ::close(fd);
  }

  [[noreturn]] void fail(DefectKind kind, const std::string& what) const {
    Finding f;
    f.kind = kind;
    f.detail = what;
    throw FileDefect(path, std::move(f));
  }
  [[noreturn]] void fail_brick(DefectKind kind, int level, int channel, std::int64_t bx,
                               std::int64_t by, std::int64_t bz, const std::string& what) const {
    throw FileDefect(path, finding(kind, level, channel, {bx, by, bz}, what));
  }
  [[noreturn]] void fail_brick(DefectKind kind, const BrickInfo& b, const std::string& what) const {
    fail_brick(kind, b.level, b.channel, b.brick[0], b.brick[1], b.brick[2], what);
  }
  Finding finding(DefectKind kind, int level, int channel, const std::array<std::int64_t, 3>& at,
                  const std::string& what) const {
    Finding f;
    f.kind = kind;
    f.has_brick = true;
    f.level = level;
    f.channel = channel;
    f.channel_name = channel >= 0 && channel < int(channels.size())
                         ? channels[std::size_t(channel)].name
                         : cat("#", channel);
    f.brick = at;
    f.detail = what;
    return f;
  }

  std::string name(const BrickInfo& b) const {
    return brick_name(channels, b.level, b.channel, b.brick[0], b.brick[1], b.brick[2]);
  }

  std::size_t brick_bytes(int channel) const {
    return std::size_t(edge) * std::size_t(edge) * std::size_t(edge) *
           channel_type_bytes(channels[std::size_t(channel)].type);
  }

  void map() {
    fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) throw IoError(cat(path, ": cannot open: ", std::strerror(errno)));
    struct stat st {};
    if (::fstat(fd, &st) != 0) throw IoError(cat(path, ": cannot stat: ", std::strerror(errno)));
    if (!S_ISREG(st.st_mode)) throw IoError(cat(path, ": not a regular file"));
    if (std::uint64_t(st.st_size) < detail::kHeaderSize) {
      fail(DefectKind::kSizeMismatch, cat("truncated or not a vispack file: ", st.st_size,
                                          " bytes, the header alone is ", detail::kHeaderSize));
    }
    size = std::size_t(st.st_size);
    void* p = ::mmap(nullptr, size, PROT_READ, MAP_SHARED, fd, 0);
    if (p == MAP_FAILED) {
      size = 0;
      throw IoError(cat(path, ": cannot map: ", std::strerror(errno)));
    }
    base = static_cast<const std::uint8_t*>(p);
  }

  // The 128-byte header (SPEC.md "Header"), checked field by field before any offset in it is
  // used: what the file is, the fixed fields, where the blocks lie, the table checksum.
  void parse_header(const ReaderLimits& limits) {
    std::memcpy(&header, base, sizeof(header));
    check_identity();
    check_header_fields();
    check_block_layout(limits);
    check_table_checksum();
  }

  // Magic, version and file size: is this a packed volume this reader can read, and whole.
  void check_identity() const {
    const FileHeader& h = header;
    if (std::memcmp(h.magic, detail::kMagic, 8) != 0) {
      if (std::memcmp(h.magic + 1, "VPK", 3) == 0) {
        fail(DefectKind::kNotVispack,
             "damaged magic (a text-mode transfer may have changed line endings)");
      }
      fail(DefectKind::kNotVispack, "not a vispack packed volume (bad magic)");
    }
    if (h.version_major > kFormatMajor) {
      fail(DefectKind::kUnsupportedVersion,
           cat("format version ", h.version_major, ".", h.version_minor,
               " is newer than this reader (", kFormatMajor, ".", kFormatMinor, ")"));
    }
    if (h.version_major == 0)
      fail(DefectKind::kUnsupportedVersion, "format major version 0 is invalid");
    if (h.file_size != size) {
      fail(DefectKind::kSizeMismatch, cat("truncated or extended: the header says ", h.file_size,
                                          " bytes, the file has ", size));
    }
  }

  // The fields with fixed or bounded values: sizes, reserved fields, brick edge, counts.
  void check_header_fields() const {
    const FileHeader& h = header;
    if (h.header_size != detail::kHeaderSize)
      fail(DefectKind::kHeaderField, cat("header_size ", h.header_size, " is not 128"));
    if (h.index_entry_size != detail::kIndexEntrySize) {
      fail(DefectKind::kHeaderField, cat("index_entry_size ", h.index_entry_size, " is not 64"));
    }
    if (h.flags != 0 || h.reserved0 != 0 || h.reserved1 != 0)
      fail(DefectKind::kHeaderField, "reserved header fields are not zero");
    if (h.brick_edge < 4 || h.brick_edge > 1024 || (h.brick_edge & (h.brick_edge - 1)) != 0) {
      fail(DefectKind::kHeaderField,
           cat("brick_edge ", h.brick_edge, " is not a power of two in [4, 1024]"));
    }
    if (h.channel_count < 1 || h.channel_count > 255)
      fail(DefectKind::kHeaderField,
           cat("channel_count ", h.channel_count, " is outside [1, 255]"));
    if (h.level_count < 1 || h.level_count > 64)
      fail(DefectKind::kHeaderField, cat("level_count ", h.level_count, " is outside [1, 64]"));
  }

  // Payloads, metadata, index and label IDs lie one after the other, inside the file, in that
  // order, with the limits' sizes.
  void check_block_layout(const ReaderLimits& limits) const {
    const FileHeader& h = header;
    if (h.payload_offset != kPayloadAlignment)
      fail(DefectKind::kHeaderField, cat("payload_offset ", h.payload_offset, " is not 4096"));
    if (h.payload_end < h.payload_offset || h.payload_end % kPayloadAlignment != 0 ||
        h.payload_end > size) {
      fail(DefectKind::kHeaderField,
           cat("payload_end ", h.payload_end, " is not a multiple of 4096 in [4096, file size ",
               size, "]"));
    }
    if (h.metadata_offset != h.payload_end)
      fail(DefectKind::kHeaderField,
           cat("metadata_offset ", h.metadata_offset, " != payload_end ", h.payload_end));
    if (h.metadata_size == 0 || h.metadata_size > limits.max_metadata_bytes) {
      fail(DefectKind::kHeaderField, cat("metadata_size ", h.metadata_size, " is outside [1, ",
                                         limits.max_metadata_bytes, "]"));
    }
    auto meta_end = add(h.metadata_offset, h.metadata_size);
    if (!meta_end || *meta_end > size)
      fail(DefectKind::kHeaderField, cat("metadata block (", h.metadata_size, " bytes at ",
                                         h.metadata_offset, ") runs past the end of the file"));
    if (h.index_offset != align_up(*meta_end, 8))
      fail(DefectKind::kHeaderField,
           cat("index_offset ", h.index_offset, " is not the metadata end rounded up to 8"));
    if (h.index_count == 0 || h.index_count > limits.max_index_entries) {
      fail(DefectKind::kHeaderField,
           cat("index_count ", h.index_count, " is outside [1, ", limits.max_index_entries, "]"));
    }
    auto index_bytes = mul(h.index_count, detail::kIndexEntrySize);
    auto index_end = index_bytes ? add(h.index_offset, *index_bytes) : std::nullopt;
    if (!index_end || *index_end > size)
      fail(DefectKind::kHeaderField, cat("brick index (", h.index_count, " entries at ",
                                         h.index_offset, ") runs past the end of the file"));
    if (h.labels_offset != *index_end)
      fail(DefectKind::kHeaderField,
           cat("labels_offset ", h.labels_offset, " is not the index end ", *index_end));
    if (h.labels_count > limits.max_label_ids)
      fail(DefectKind::kHeaderField,
           cat("labels_count ", h.labels_count, " exceeds the limit ", limits.max_label_ids));
    auto labels_end = add(h.labels_offset, h.labels_count * 4);
    if (!labels_end || *labels_end != size)
      fail(DefectKind::kHeaderField, cat("label IDs (", h.labels_count, " at ", h.labels_offset,
                                         ") do not end at the file end ", size));
  }

  // xxHash64 of header[0, 120) and everything from the metadata to the end of the file.
  void check_table_checksum() const {
    const FileHeader& h = header;
    XXH64_state_t* state = XXH64_createState();
    if (!state) throw std::bad_alloc();
    XXH64_reset(state, 0);
    XXH64_update(state, base, detail::kChecksumFieldOffset);
    XXH64_update(state, base + h.metadata_offset,
                 std::size_t(h.labels_offset + h.labels_count * 4 - h.metadata_offset));
    std::uint64_t sum = XXH64_digest(state);
    XXH64_freeState(state);
    if (sum != h.table_checksum) {
      fail(DefectKind::kTableChecksum,
           cat("table checksum mismatch (header, metadata, index, label IDs): stored ",
               hex64(h.table_checksum), ", computed ", hex64(sum)));
    }
  }

  void parse_metadata(const ReaderLimits& limits) {
    const char* text = reinterpret_cast<const char*>(base + header.metadata_offset);
    VolumeMetadata m;
    try {
      m = format::parse_metadata(path, text, std::size_t(header.metadata_size), limits, &meta);
    } catch (const FormatError& e) {
      // The core's message starts with "<path>: "; the finding carries the rest.
      std::string what = e.what();
      const std::string prefix = path + ": ";
      if (what.compare(0, prefix.size(), prefix) == 0) what.erase(0, prefix.size());
      fail(DefectKind::kMetadata, what);
    }
    edge = m.brick_edge;
    if (std::uint32_t(edge) != header.brick_edge)
      fail(DefectKind::kMetadata, cat("metadata key \"brick_edge\" = ", edge,
                                      " differs from the header's ", header.brick_edge));
    if (m.channels.size() != header.channel_count)
      fail(DefectKind::kMetadata, cat("metadata key \"channels\" has ", m.channels.size(),
                                      " entries, the header says ", header.channel_count));
    channels = std::move(m.channels);
    label_table = std::move(m.label_table);
    // Levels follow from dims and brick_edge alone (geometry.h, shared with the writer).
    auto g = make_geometry(m.dims, m.spacing_mm, m.origin_mm, edge, int(channels.size()),
                           limits.max_index_entries);
    if (!g) {
      fail(DefectKind::kMetadata,
           cat("dims ", m.dims[0], "x", m.dims[1], "x", m.dims[2],
               " need more bricks than the limit ", limits.max_index_entries));
    }
    geometry = std::move(*g);
    if (geometry.levels.size() != header.level_count) {
      fail(DefectKind::kMetadata,
           cat("level_count ", header.level_count, " in the header, but dims and brick_edge give ",
               geometry.levels.size()));
    }
    if (geometry.index_count != header.index_count) {
      fail(DefectKind::kMetadata,
           cat("index_count ", header.index_count,
               " in the header, but dims, channels and levels give ", geometry.index_count));
    }
  }

  // A payload's byte range and its brick (for the overlap check).
  struct PayloadSpan {
    std::uint64_t offset, end;
    std::size_t k;
  };

  // The brick index (SPEC.md "Brick index"): one entry per brick in level, channel, z, y, x
  // order, each checked (parse_entry) before it is used, then the payloads' layout.
  void parse_index() {
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

  // Index entry k, expected to describe brick `at` of level l, channel c: read into bricks[k],
  // its payload's range appended to `spans`. Throws FileDefect naming the brick.
  void parse_entry(std::size_t k, int l, int c, const std::array<std::int64_t, 3>& at,
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
      if (e.min[i] != 0 || e.max[i] != 0)
        bad(cat("min/max bytes past the voxel size are not zero"));
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

  // The codec and its payload: a uniform brick has none; a raw one is exactly `raw_bytes`, a
  // zstd one smaller; both aligned and inside the payload area. Sets b.codec.
  template <typename Bad>
  void check_entry_codec(const IndexEntry& e, BrickInfo& b, std::uint64_t raw_bytes,
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

  // A label channel's brick names a non-empty, strictly ascending run of the file's label IDs
  // that matches its min and max; any other channel's brick names none.
  template <typename Bad>
  void check_entry_labels(const IndexEntry& e, const BrickInfo& b, ChannelType type,
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

  // Payloads do not overlap, and the last one's aligned end is payload_end.
  void check_payload_spans(std::vector<PayloadSpan>& spans) const {
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

  // Reader::check's parts (defined after the Reader's members).
  std::optional<Finding> check_brick(const BrickInfo& b, bool deep) const;
  std::optional<Finding> check_decoded(const BrickInfo& b,
                                       const std::vector<std::uint8_t>& buf) const;
  void check_padding(std::vector<Finding>& findings) const;

  ZSTD_DCtx* acquire() const {
    {
      std::lock_guard<std::mutex> lock(dctx_mutex);
      if (!dctx_free.empty()) {
        ZSTD_DCtx* d = dctx_free.back();
        dctx_free.pop_back();
        return d;
      }
    }
    ZSTD_DCtx* d = ZSTD_createDCtx();
    if (!d) throw std::bad_alloc();
    return d;
  }
  void release(ZSTD_DCtx* d) const {
    std::lock_guard<std::mutex> lock(dctx_mutex);
    dctx_free.push_back(d);
  }

  void decode(const BrickInfo& b, void* out, std::size_t out_size, bool verify_checksum) const {
    const std::size_t n = brick_bytes(b.channel);
    if (out_size < n)
      throw std::invalid_argument(
          cat(path, ": ", name(b), ": output buffer of ", out_size, " bytes, need ", n));
    const std::uint8_t* payload = base + b.offset;
    if (verify_checksum && b.codec != Codec::kUniform) {
      std::uint64_t sum = xxh64(payload, std::size_t(b.stored_size));
      if (sum != b.checksum)
        fail_brick(DefectKind::kPayloadChecksum, b,
                   cat("payload checksum mismatch (stored ", hex64(b.checksum), ", computed ",
                       hex64(sum), ")"));
    }
    switch (b.codec) {
      case Codec::kUniform: {
        const std::size_t vb = channel_type_bytes(channels[std::size_t(b.channel)].type);
        auto* o = static_cast<std::uint8_t*>(out);
        if (vb == 1) {
          std::memset(o, b.uniform[0], n);
        } else {
          for (std::size_t i = 0; i < n; i += vb)
            std::memcpy(o + i, b.uniform.data(), vb);
        }
        break;
      }
      case Codec::kRaw:
        std::memcpy(out, payload, n);
        break;
      case Codec::kZstd: {
        ZSTD_DCtx* d = acquire();
        std::size_t r = ZSTD_decompressDCtx(d, out, n, payload, std::size_t(b.stored_size));
        release(d);
        if (ZSTD_isError(r))
          fail_brick(DefectKind::kPayloadDecode, b,
                     cat("zstd payload does not decode: ", ZSTD_getErrorName(r)));
        if (r != n)
          fail_brick(DefectKind::kPayloadDecode, b,
                     cat("zstd payload decodes to ", r, " bytes, expected ", n));
        break;
      }
    }
  }

  const BrickInfo& brick(int channel, int level, std::int64_t bx, std::int64_t by,
                         std::int64_t bz) const {
    if (level < 0 || level >= int(levels.size()))
      throw std::out_of_range(cat(path, ": level ", level, " outside [0, ", levels.size(), ")"));
    if (channel < 0 || channel >= int(channels.size()))
      throw std::out_of_range(
          cat(path, ": channel ", channel, " outside [0, ", channels.size(), ")"));
    const LevelInfo& li = levels[std::size_t(level)];
    if (bx < 0 || by < 0 || bz < 0 || bx >= li.bricks[0] || by >= li.bricks[1] ||
        bz >= li.bricks[2]) {
      throw std::out_of_range(
          cat(path, ": brick (", bx, ",", by, ",", bz, ") outside the level ", level, " grid"));
    }
    return bricks[std::size_t(geometry.entry(level, channel, bx, by, bz))];
  }

  // Copies the part of brick `b` inside the box into `out` (the box's buffer). `tmp` is a
  // scratch buffer of brick_bytes used for zstd bricks.
  void copy_brick(const BrickInfo& b, const std::array<std::int64_t, 3>& o,
                  const std::array<std::int64_t, 3>& n, std::uint8_t* out,
                  std::vector<std::uint8_t>& tmp) const {
    const std::size_t vb = channel_type_bytes(channels[std::size_t(b.channel)].type);
    const std::int64_t e = edge;
    std::array<std::int64_t, 3> lo{}, hi{};
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::max(o[a], b.brick[a] * e);
      hi[a] = std::min(o[a] + n[a], (b.brick[a] + 1) * e);
    }
    const std::size_t row = std::size_t(hi[0] - lo[0]) * vb;
    if (b.codec == Codec::kUniform) {
      for (std::int64_t z = lo[2]; z < hi[2]; ++z) {
        for (std::int64_t y = lo[1]; y < hi[1]; ++y) {
          std::uint8_t* dst =
              out + (std::size_t((z - o[2]) * n[1] + (y - o[1])) * std::size_t(n[0]) +
                     std::size_t(lo[0] - o[0])) *
                        vb;
          if (vb == 1)
            std::memset(dst, b.uniform[0], row);
          else
            for (std::size_t i = 0; i < row; i += vb)
              std::memcpy(dst + i, b.uniform.data(), vb);
        }
      }
      return;
    }
    const std::uint8_t* src = nullptr;
    if (b.codec == Codec::kRaw) {
      src = base + b.offset;
    } else {
      tmp.resize(brick_bytes(b.channel));
      decode(b, tmp.data(), tmp.size(), false);
      src = tmp.data();
    }
    for (std::int64_t z = lo[2]; z < hi[2]; ++z) {
      for (std::int64_t y = lo[1]; y < hi[1]; ++y) {
        const std::uint8_t* s =
            src + (std::size_t(((z - b.brick[2] * e) * e + (y - b.brick[1] * e)) * e +
                               (lo[0] - b.brick[0] * e))) *
                      vb;
        std::uint8_t* dst = out + (std::size_t((z - o[2]) * n[1] + (y - o[1])) * std::size_t(n[0]) +
                                   std::size_t(lo[0] - o[0])) *
                                      vb;
        std::memcpy(dst, s, row);
      }
    }
  }

  void region(int channel, int level, const std::array<std::int64_t, 3>& o,
              const std::array<std::int64_t, 3>& n, void* out, int threads) const {
    if (level < 0 || level >= int(levels.size()))
      throw std::out_of_range(cat(path, ": level ", level, " outside [0, ", levels.size(), ")"));
    if (channel < 0 || channel >= int(channels.size()))
      throw std::out_of_range(
          cat(path, ": channel ", channel, " outside [0, ", channels.size(), ")"));
    const LevelInfo& li = levels[std::size_t(level)];
    for (int a = 0; a < 3; ++a) {
      if (o[a] < 0 || n[a] < 0 || o[a] > li.dims[a] || n[a] > li.dims[a] - o[a]) {
        throw std::out_of_range(cat(path, ": region [", o[0], ",", o[1], ",", o[2], "] + [", n[0],
                                    ",", n[1], ",", n[2], "] is not inside level ", level, " (",
                                    li.dims[0], "x", li.dims[1], "x", li.dims[2], ")"));
      }
    }
    if (n[0] == 0 || n[1] == 0 || n[2] == 0) return;
    std::array<std::int64_t, 3> b0{}, b1{};
    for (int a = 0; a < 3; ++a) {
      b0[a] = o[a] / edge;
      b1[a] = (o[a] + n[a] - 1) / edge + 1;
    }
    const std::int64_t cx = b1[0] - b0[0], cy = b1[1] - b0[1], cz = b1[2] - b0[2];
    auto* dst = static_cast<std::uint8_t*>(out);
    if (threads == 1 || cx * cy * cz == 1) {
      std::vector<std::uint8_t> tmp;
      for (std::int64_t bz = b0[2]; bz < b1[2]; ++bz)
        for (std::int64_t by = b0[1]; by < b1[1]; ++by)
          for (std::int64_t bx = b0[0]; bx < b1[0]; ++bx)
            copy_brick(brick(channel, level, bx, by, bz), o, n, dst, tmp);
      return;
    }
    parallel_for(cx * cy * cz, threads, [&](std::int64_t i) {
      std::vector<std::uint8_t> tmp;
      std::int64_t bx = b0[0] + i % cx, by = b0[1] + (i / cx) % cy, bz = b0[2] + i / (cx * cy);
      copy_brick(brick(channel, level, bx, by, bz), o, n, dst, tmp);
    });
  }
};

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

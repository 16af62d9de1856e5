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
#include <cmath>
#include <cstring>
#include <limits>
#include <mutex>
#include <stdexcept>
#include <unordered_set>

#include "layout.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"

namespace vispack::format {
namespace {

using detail::align_up;
using detail::FileHeader;
using detail::IndexEntry;
using nlohmann::json;

constexpr int kMaxJsonDepth = 64;

// a * b, or nullopt when it overflows uint64.
std::optional<std::uint64_t> mul(std::uint64_t a, std::uint64_t b) {
  if (a != 0 && b > std::numeric_limits<std::uint64_t>::max() / a) return std::nullopt;
  return a * b;
}
std::optional<std::uint64_t> add(std::uint64_t a, std::uint64_t b) {
  if (b > std::numeric_limits<std::uint64_t>::max() - a) return std::nullopt;
  return a + b;
}

std::int64_t ceil_div(std::int64_t a, std::int64_t b) {
  return (a + b - 1) / b;
}

// Rejects JSON nested deeper than kMaxJsonDepth before the parser sees it.
void check_json_depth(const std::string& path, const char* text, std::size_t size) {
  int depth = 0;
  bool in_string = false, escape = false;
  for (std::size_t i = 0; i < size; ++i) {
    char ch = text[i];
    if (in_string) {
      if (escape)
        escape = false;
      else if (ch == '\\')
        escape = true;
      else if (ch == '"')
        in_string = false;
      continue;
    }
    if (ch == '"')
      in_string = true;
    else if (ch == '[' || ch == '{') {
      if (++depth > kMaxJsonDepth) {
        throw FormatError(cat(path, ": metadata JSON nested deeper than ", kMaxJsonDepth,
                              " levels (at byte ", i, ")"));
      }
    } else if (ch == ']' || ch == '}') {
      --depth;
    }
  }
}

// Typed access to metadata keys with one clear error per bad key.
class MetaReader {
 public:
  MetaReader(const std::string& path, const json& root) : path_(path), root_(root) {}

  const json& get(const json& obj, const std::string& key, const char* where = "") const {
    if (!obj.is_object()) fail(key, cat("parent of \"", key, "\" is not an object", where));
    auto it = obj.find(key);
    if (it == obj.end()) fail(key, "is missing");
    return *it;
  }
  std::int64_t integer(const json& v, const std::string& key, std::int64_t lo,
                       std::int64_t hi) const {
    if (!v.is_number_integer()) fail(key, "is not an integer");
    if (v.is_number_unsigned() && v.get<std::uint64_t>() > std::uint64_t(hi)) {
      fail(key, cat("= ", v.get<std::uint64_t>(), " is outside [", lo, ", ", hi, "]"));
    }
    std::int64_t x = v.get<std::int64_t>();
    if (x < lo || x > hi) fail(key, cat("= ", x, " is outside [", lo, ", ", hi, "]"));
    return x;
  }
  double number(const json& v, const std::string& key) const {
    if (!v.is_number()) fail(key, "is not a number");
    double x = v.get<double>();
    if (!std::isfinite(x)) fail(key, "is not finite");
    return x;
  }
  std::string string(const json& v, const std::string& key) const {
    if (!v.is_string()) fail(key, "is not a string");
    return v.get<std::string>();
  }
  const json& array(const json& v, const std::string& key, std::size_t min_size,
                    std::size_t max_size) const {
    if (!v.is_array()) fail(key, "is not an array");
    if (v.size() < min_size || v.size() > max_size) {
      fail(key, cat("has ", v.size(), " elements, expected ", min_size, "..", max_size));
    }
    return v;
  }
  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    throw FormatError(cat(path_, ": metadata key \"", key, "\" ", what));
  }

 private:
  const std::string& path_;
  const json& root_;
};

std::string brick_name(const std::vector<ChannelSpec>& channels, int level, int channel,
                       std::int64_t bx, std::int64_t by, std::int64_t bz) {
  std::string name =
      channel >= 0 && channel < int(channels.size()) ? channels[channel].name : cat("#", channel);
  return cat("brick level ", level, " channel ", name, " (", bx, ",", by, ",", bz, ")");
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
  std::vector<LevelInfo> levels;
  std::vector<std::uint64_t> level_base;
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

  [[noreturn]] void fail(const std::string& what) const {
    throw FormatError(cat(path, ": ", what));
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
      fail(cat("truncated or not a vispack file: ", st.st_size, " bytes, the header alone is ",
               detail::kHeaderSize));
    }
    size = std::size_t(st.st_size);
    void* p = ::mmap(nullptr, size, PROT_READ, MAP_SHARED, fd, 0);
    if (p == MAP_FAILED) {
      size = 0;
      throw IoError(cat(path, ": cannot map: ", std::strerror(errno)));
    }
    base = static_cast<const std::uint8_t*>(p);
  }

  void parse_header(const ReaderLimits& limits) {
    std::memcpy(&header, base, sizeof(header));
    const FileHeader& h = header;
    if (std::memcmp(h.magic, detail::kMagic, 8) != 0) {
      if (std::memcmp(h.magic + 1, "VPK", 3) == 0) {
        fail("damaged magic (a text-mode transfer may have changed line endings)");
      }
      fail("not a vispack packed volume (bad magic)");
    }
    if (h.version_major > kFormatMajor) {
      fail(cat("format version ", h.version_major, ".", h.version_minor,
               " is newer than this reader (", kFormatMajor, ".", kFormatMinor, ")"));
    }
    if (h.version_major == 0) fail("format major version 0 is invalid");
    if (h.file_size != size) {
      fail(cat("truncated or extended: the header says ", h.file_size, " bytes, the file has ",
               size));
    }
    if (h.header_size != detail::kHeaderSize)
      fail(cat("header_size ", h.header_size, " is not 128"));
    if (h.index_entry_size != detail::kIndexEntrySize) {
      fail(cat("index_entry_size ", h.index_entry_size, " is not 64"));
    }
    if (h.flags != 0 || h.reserved0 != 0 || h.reserved1 != 0)
      fail("reserved header fields are not zero");
    if (h.brick_edge < 4 || h.brick_edge > 1024 || (h.brick_edge & (h.brick_edge - 1)) != 0) {
      fail(cat("brick_edge ", h.brick_edge, " is not a power of two in [4, 1024]"));
    }
    if (h.channel_count < 1 || h.channel_count > 255)
      fail(cat("channel_count ", h.channel_count, " is outside [1, 255]"));
    if (h.level_count < 1 || h.level_count > 64)
      fail(cat("level_count ", h.level_count, " is outside [1, 64]"));
    if (h.payload_offset != kPayloadAlignment)
      fail(cat("payload_offset ", h.payload_offset, " is not 4096"));
    if (h.payload_end < h.payload_offset || h.payload_end % kPayloadAlignment != 0 ||
        h.payload_end > size) {
      fail(cat("payload_end ", h.payload_end, " is not a multiple of 4096 in [4096, file size ",
               size, "]"));
    }
    if (h.metadata_offset != h.payload_end)
      fail(cat("metadata_offset ", h.metadata_offset, " != payload_end ", h.payload_end));
    if (h.metadata_size == 0 || h.metadata_size > limits.max_metadata_bytes) {
      fail(cat("metadata_size ", h.metadata_size, " is outside [1, ", limits.max_metadata_bytes,
               "]"));
    }
    auto meta_end = add(h.metadata_offset, h.metadata_size);
    if (!meta_end || *meta_end > size)
      fail(cat("metadata block (", h.metadata_size, " bytes at ", h.metadata_offset,
               ") runs past the end of the file"));
    if (h.index_offset != align_up(*meta_end, 8))
      fail(cat("index_offset ", h.index_offset, " is not the metadata end rounded up to 8"));
    if (h.index_count == 0 || h.index_count > limits.max_index_entries) {
      fail(cat("index_count ", h.index_count, " is outside [1, ", limits.max_index_entries, "]"));
    }
    auto index_bytes = mul(h.index_count, detail::kIndexEntrySize);
    auto index_end = index_bytes ? add(h.index_offset, *index_bytes) : std::nullopt;
    if (!index_end || *index_end > size)
      fail(cat("brick index (", h.index_count, " entries at ", h.index_offset,
               ") runs past the end of the file"));
    if (h.labels_offset != *index_end)
      fail(cat("labels_offset ", h.labels_offset, " is not the index end ", *index_end));
    if (h.labels_count > limits.max_label_ids)
      fail(cat("labels_count ", h.labels_count, " exceeds the limit ", limits.max_label_ids));
    auto labels_end = add(h.labels_offset, h.labels_count * 4);
    if (!labels_end || *labels_end != size)
      fail(cat("label IDs (", h.labels_count, " at ", h.labels_offset,
               ") do not end at the file end ", size));

    XXH64_state_t* state = XXH64_createState();
    if (!state) throw std::bad_alloc();
    XXH64_reset(state, 0);
    XXH64_update(state, base, detail::kChecksumFieldOffset);
    XXH64_update(state, base + h.metadata_offset,
                 std::size_t(h.labels_offset + h.labels_count * 4 - h.metadata_offset));
    std::uint64_t sum = XXH64_digest(state);
    XXH64_freeState(state);
    // Covers header[0, 120) and everything from the metadata to the end of the file.
    if (sum != h.table_checksum) {
      fail(cat("table checksum mismatch (header, metadata, index, label IDs): stored ",
               hex64(h.table_checksum), ", computed ", hex64(sum)));
    }
  }

  void parse_metadata(const ReaderLimits& limits) {
    const char* text = reinterpret_cast<const char*>(base + header.metadata_offset);
    const std::size_t n = std::size_t(header.metadata_size);
    check_json_depth(path, text, n);
    try {
      meta = json::parse(text, text + n);
    } catch (const json::exception& e) {
      fail(cat("malformed metadata JSON: ", e.what()));
    }
    MetaReader r(path, meta);
    if (!meta.is_object()) fail("metadata JSON is not an object");
    if (r.string(r.get(meta, "format"), "format") != "vispack")
      r.fail("format", "is not \"vispack\"");
    const json& dims_j = r.array(r.get(meta, "dims"), "dims", 3, 3);
    std::array<std::int64_t, 3> dims{};
    for (int a = 0; a < 3; ++a)
      dims[a] = r.integer(dims_j[a], "dims", 1, limits.max_dim);
    auto voxels = mul(std::uint64_t(dims[0]), std::uint64_t(dims[1]));
    if (voxels) voxels = mul(*voxels, std::uint64_t(dims[2]));
    if (!voxels || *voxels > limits.max_level_voxels) {
      r.fail("dims", cat(dims[0], "x", dims[1], "x", dims[2], " exceed the limit of ",
                         limits.max_level_voxels, " voxels"));
    }
    std::array<double, 3> spacing{}, origin{};
    const json& sp = r.array(r.get(meta, "spacing_mm"), "spacing_mm", 3, 3);
    const json& org = r.array(r.get(meta, "origin_mm"), "origin_mm", 3, 3);
    for (int a = 0; a < 3; ++a) {
      spacing[a] = r.number(sp[a], "spacing_mm");
      if (!(spacing[a] > 0)) r.fail("spacing_mm", "has a value <= 0");
      origin[a] = r.number(org[a], "origin_mm");
    }
    edge = int(r.integer(r.get(meta, "brick_edge"), "brick_edge", 4, 1024));
    if (std::uint32_t(edge) != header.brick_edge)
      r.fail("brick_edge", cat("= ", edge, " differs from the header's ", header.brick_edge));
    const json& ch = r.array(r.get(meta, "channels"), "channels", 1, 255);
    if (ch.size() != header.channel_count)
      r.fail("channels",
             cat("has ", ch.size(), " entries, the header says ", header.channel_count));
    std::unordered_set<std::string> names;
    for (const json& c : ch) {
      ChannelSpec s;
      s.name = r.string(r.get(c, "name"), "channels[].name");
      if (s.name.empty() || !names.insert(s.name).second)
        r.fail("channels[].name", cat("\"", s.name, "\" is empty or repeated"));
      try {
        s.type = channel_type_from_name(r.string(r.get(c, "type"), "channels[].type"));
      } catch (const FormatError& e) {
        r.fail("channels[].type", e.what());
      }
      channels.push_back(s);
    }
    if (meta.contains("label_table")) {
      const json& lt = r.array(meta["label_table"], "label_table", 0, 65535);
      for (const json& l : lt) {
        LabelEntry e;
        e.id = std::uint32_t(r.integer(r.get(l, "id"), "label_table[].id", 1, 65535));
        e.name = r.string(r.get(l, "name"), "label_table[].name");
        const json& col = r.array(r.get(l, "colour"), "label_table[].colour", 3, 3);
        for (int k = 0; k < 3; ++k)
          e.colour[k] = std::uint8_t(r.integer(col[k], "label_table[].colour", 0, 255));
        label_table.push_back(std::move(e));
      }
    }
    // Levels follow from dims and brick_edge alone.
    std::array<std::int64_t, 3> d = dims;
    std::uint64_t total = 0;
    for (int l = 0;; ++l) {
      LevelInfo li;
      li.dims = d;
      for (int a = 0; a < 3; ++a) {
        li.bricks[a] = ceil_div(d[a], edge);
        double f = std::ldexp(1.0, l);
        li.spacing_mm[a] = spacing[a] * f;
        li.origin_mm[a] = origin[a] + (f - 1) / 2 * spacing[a];
      }
      level_base.push_back(total);
      auto g = mul(std::uint64_t(li.bricks[0]), std::uint64_t(li.bricks[1]));
      if (g) g = mul(*g, std::uint64_t(li.bricks[2]));
      if (g) g = mul(*g, channels.size());
      if (g) g = add(total, *g);
      if (!g || *g > limits.max_index_entries)
        fail(cat("dims ", dims[0], "x", dims[1], "x", dims[2], " need more bricks than the limit ",
                 limits.max_index_entries));
      total = *g;
      levels.push_back(li);
      if (d[0] <= edge && d[1] <= edge && d[2] <= edge) break;
      for (auto& v : d)
        v = ceil_div(v, 2);
    }
    if (levels.size() != header.level_count) {
      fail(cat("level_count ", header.level_count, " in the header, but dims and brick_edge give ",
               levels.size()));
    }
    if (total != header.index_count) {
      fail(cat("index_count ", header.index_count,
               " in the header, but dims, channels and levels give ", total));
    }
  }

  void parse_index() {
    const FileHeader& h = header;
    label_ids.resize(std::size_t(h.labels_count));
    if (h.labels_count)
      std::memcpy(label_ids.data(), base + h.labels_offset, std::size_t(h.labels_count) * 4);
    bricks.resize(std::size_t(h.index_count));
    struct Span {
      std::uint64_t offset, end;
      std::size_t k;
    };
    std::vector<Span> spans;
    std::size_t k = 0;
    for (int l = 0; l < int(levels.size()); ++l) {
      const LevelInfo& li = levels[std::size_t(l)];
      for (int c = 0; c < int(channels.size()); ++c) {
        const ChannelType type = channels[std::size_t(c)].type;
        const std::size_t vbytes = channel_type_bytes(type);
        const std::uint64_t raw_bytes = brick_bytes(c);
        for (std::int64_t bz = 0; bz < li.bricks[2]; ++bz) {
          for (std::int64_t by = 0; by < li.bricks[1]; ++by) {
            for (std::int64_t bx = 0; bx < li.bricks[0]; ++bx, ++k) {
              IndexEntry e;
              std::memcpy(&e, base + h.index_offset + k * sizeof(IndexEntry), sizeof(e));
              const std::string who = brick_name(channels, l, c, bx, by, bz);
              if (e.level != l || e.channel != c || e.bx != bx || e.by != by || e.bz != bz) {
                fail(cat("index entry ", k, " is for level ", int(e.level), " channel ",
                         int(e.channel), " (", e.bx, ",", e.by, ",", e.bz, "), expected ", who));
              }
              if (e.reserved != 0) fail(cat(who, ": reserved byte is not zero"));
              for (std::size_t i = vbytes; i < 8; ++i) {
                if (e.min[i] != 0 || e.max[i] != 0)
                  fail(cat(who, ": min/max bytes past the voxel size are not zero"));
              }
              BrickInfo& b = bricks[k];
              b.level = l;
              b.channel = c;
              b.brick = {bx, by, bz};
              b.offset = e.offset;
              b.stored_size = e.stored_size;
              b.checksum = e.checksum;
              b.min = decode_value(type, e.min);
              b.max = decode_value(type, e.max);
              std::memcpy(b.uniform.data(), e.min, 4);
              b.label_first = e.label_first;
              b.label_count = e.label_count;
              for (int comp = 0; comp < 4; ++comp) {
                if (b.min[comp] > b.max[comp]) fail(cat(who, ": min > max"));
              }
              switch (e.codec) {
                case std::uint8_t(Codec::kUniform):
                  b.codec = Codec::kUniform;
                  if (e.offset || e.stored_size || e.checksum)
                    fail(cat(who, ": uniform brick with a payload offset, size or checksum"));
                  if (std::memcmp(e.min, e.max, 8) != 0)
                    fail(cat(who, ": uniform brick with min != max"));
                  break;
                case std::uint8_t(Codec::kRaw):
                case std::uint8_t(Codec::kZstd): {
                  b.codec = Codec(e.codec);
                  if (b.codec == Codec::kRaw && e.stored_size != raw_bytes)
                    fail(
                        cat(who, ": raw brick of ", e.stored_size, " bytes, expected ", raw_bytes));
                  if (b.codec == Codec::kZstd && (e.stored_size == 0 || e.stored_size >= raw_bytes))
                    fail(cat(who, ": zstd brick of ", e.stored_size, " bytes (must be in [1, ",
                             raw_bytes, "))"));
                  if (e.offset % kPayloadAlignment != 0)
                    fail(cat(who, ": payload offset ", e.offset, " is not a multiple of 4096"));
                  auto end = add(e.offset, e.stored_size);
                  if (e.offset < h.payload_offset || !end || *end > h.payload_end) {
                    fail(cat(who, ": payload [", e.offset, ", +", e.stored_size,
                             ") lies outside the payload area [", h.payload_offset, ", ",
                             h.payload_end, ")"));
                  }
                  spans.push_back({e.offset, *end, k});
                  break;
                }
                default:
                  fail(cat(who, ": unknown codec ", int(e.codec)));
              }
              if (is_label_type(type)) {
                if (e.label_count == 0 ||
                    std::uint64_t(e.label_first) + e.label_count > h.labels_count) {
                  fail(cat(who, ": label set [", e.label_first, ", +", e.label_count,
                           ") is empty or outside the ", h.labels_count, " label IDs"));
                }
                const std::uint32_t limit = type == ChannelType::kUint8 ? 255 : 65535;
                const std::uint32_t* ids = label_ids.data() + e.label_first;
                for (std::uint32_t i = 0; i < e.label_count; ++i) {
                  if (ids[i] > limit || (i > 0 && ids[i] <= ids[i - 1]))
                    fail(cat(who, ": label set is not strictly ascending within the type's range"));
                }
                if (ids[0] != std::uint64_t(b.min[0]) ||
                    ids[e.label_count - 1] != std::uint64_t(b.max[0])) {
                  fail(cat(who, ": label set does not match min/max"));
                }
              } else if (e.label_count != 0 || e.label_first != 0) {
                fail(cat(who, ": label set on a channel that is not a label channel"));
              }
            }
          }
        }
      }
    }
    std::sort(spans.begin(), spans.end(),
              [](const Span& a, const Span& b) { return a.offset < b.offset; });
    std::uint64_t cursor = h.payload_offset;
    for (const Span& s : spans) {
      if (s.offset < cursor)
        fail(cat(name(bricks[s.k]), ": payload at ", s.offset,
                 " overlaps the previous brick (which ends at ", cursor, ")"));
      cursor = align_up(s.end, kPayloadAlignment);
    }
    if (cursor != h.payload_end)
      fail(cat("payload_end ", h.payload_end, " is not the aligned end of the last payload ",
               cursor));
  }

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
        fail(cat(name(b), ": checksum mismatch (stored ", hex64(b.checksum), ", computed ",
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
          fail(cat(name(b), ": zstd payload does not decode: ", ZSTD_getErrorName(r)));
        if (r != n) fail(cat(name(b), ": zstd payload decodes to ", r, " bytes, expected ", n));
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
    std::uint64_t per = std::uint64_t(li.bricks[0] * li.bricks[1] * li.bricks[2]);
    std::uint64_t k = level_base[std::size_t(level)] + std::uint64_t(channel) * per +
                      std::uint64_t((bz * li.bricks[1] + by) * li.bricks[0] + bx);
    return bricks[std::size_t(k)];
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

VerifyResult Reader::verify(bool deep, int threads) const {
  const Impl& m = *impl_;
  const std::size_t count = m.bricks.size();
  std::vector<std::string> problems(count);
  std::atomic<std::size_t> first_bad{count};
  parallel_for(std::int64_t(count), resolve_threads(threads), [&](std::int64_t i) {
    const BrickInfo& b = m.bricks[std::size_t(i)];
    if (std::size_t(i) > first_bad.load()) return;
    std::string problem;
    if (b.codec != Codec::kUniform) {
      std::uint64_t sum = xxh64(m.base + b.offset, std::size_t(b.stored_size));
      if (sum != b.checksum)
        problem =
            cat("checksum mismatch (stored ", hex64(b.checksum), ", computed ", hex64(sum), ")");
    }
    if (problem.empty() && deep) {
      std::vector<std::uint8_t> buf(m.brick_bytes(b.channel));
      try {
        m.decode(b, buf.data(), buf.size(), false);
        const ChannelType type = m.channels[std::size_t(b.channel)].type;
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
        for (int c = 0; c < channel_type_components(type); ++c) {
          if (lo[c] != b.min[c] || hi[c] != b.max[c])
            problem = "decoded min/max differ from the index";
        }
        if (!seen.empty()) {
          std::vector<std::uint32_t> ids;
          for (std::uint32_t id = 0; id < 65536; ++id)
            if (seen[id]) ids.push_back(id);
          if (ids != brick_labels(b)) problem = "decoded label set differs from the index";
        }
      } catch (const FormatError& e) {
        problem = e.what();
      }
    }
    if (!problem.empty()) {
      problems[std::size_t(i)] = problem;
      std::size_t cur = first_bad.load();
      while (std::size_t(i) < cur && !first_bad.compare_exchange_weak(cur, std::size_t(i))) {
      }
    }
  });
  VerifyResult result;
  if (first_bad.load() < count) {
    const BrickInfo& b = m.bricks[first_bad.load()];
    result.ok = false;
    result.brick = b;
    result.message = cat(m.path, ": ", m.name(b), ": ", problems[first_bad.load()]);
    return result;
  }
  // Padding: every byte outside the header, payloads, metadata, index and label IDs is zero.
  auto check_zero = [&](std::uint64_t from, std::uint64_t to, const BrickInfo* after) -> bool {
    for (std::uint64_t p = from; p < to; ++p) {
      if (m.base[p] != 0) {
        result.ok = false;
        result.message = cat(m.path, ": non-zero padding byte at offset ", p,
                             after ? cat(" (after ", m.name(*after), ")") : std::string());
        if (after) result.brick = *after;
        return false;
      }
    }
    return true;
  };
  if (!check_zero(detail::kHeaderSize, m.header.payload_offset, nullptr)) return result;
  std::vector<const BrickInfo*> stored;
  for (const BrickInfo& b : m.bricks)
    if (b.codec != Codec::kUniform) stored.push_back(&b);
  std::sort(stored.begin(), stored.end(),
            [](const BrickInfo* a, const BrickInfo* b) { return a->offset < b->offset; });
  for (std::size_t i = 0; i < stored.size(); ++i) {
    std::uint64_t end = stored[i]->offset + stored[i]->stored_size;
    std::uint64_t next = i + 1 < stored.size() ? stored[i + 1]->offset : m.header.payload_end;
    if (!check_zero(end, next, stored[i])) return result;
  }
  if (!check_zero(m.header.metadata_offset + m.header.metadata_size, m.header.index_offset,
                  nullptr))
    return result;
  return result;
}

}  // namespace vispack::format

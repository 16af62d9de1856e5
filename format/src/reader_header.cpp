// Reader::Impl: the mapped file, its header and metadata, checked before use (reader_impl.h).
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

void Reader::Impl::map() {
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

void Reader::Impl::parse_header(const ReaderLimits& limits) {
  std::memcpy(&header, base, sizeof(header));
  check_identity();
  check_header_fields();
  check_block_layout(limits);
  check_table_checksum();
}

void Reader::Impl::check_identity() const {
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

void Reader::Impl::check_header_fields() const {
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
    fail(DefectKind::kHeaderField, cat("channel_count ", h.channel_count, " is outside [1, 255]"));
  if (h.level_count < 1 || h.level_count > 64)
    fail(DefectKind::kHeaderField, cat("level_count ", h.level_count, " is outside [1, 64]"));
}

void Reader::Impl::check_block_layout(const ReaderLimits& limits) const {
  const FileHeader& h = header;
  if (h.payload_offset != kPayloadAlignment)
    fail(DefectKind::kHeaderField, cat("payload_offset ", h.payload_offset, " is not 4096"));
  if (h.payload_end < h.payload_offset || h.payload_end % kPayloadAlignment != 0 ||
      h.payload_end > size) {
    fail(DefectKind::kHeaderField,
         cat("payload_end ", h.payload_end, " is not a multiple of 4096 in [4096, file size ", size,
             "]"));
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

void Reader::Impl::check_table_checksum() const {
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

void Reader::Impl::parse_metadata(const ReaderLimits& limits) {
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
    fail(DefectKind::kMetadata, cat("dims ", m.dims[0], "x", m.dims[1], "x", m.dims[2],
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

}  // namespace vispack::format

// Writer::Impl: the end of the file, metadata, brick index, label IDs and header (writer_impl.h).
#include "vispack/format/writer.h"

#include <xxhash.h>
#include <zstd.h>

#include <algorithm>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <exception>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <unordered_set>
#include <utility>

#include "layout.h"
#include "spill_store.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"
#include "vispack/common/zero_paged_buffer.h"
#include "vispack/format/downsample.h"
#include "vispack/format/geometry.h"
#include "vispack/format/limits.h"
#include "vispack/format/metadata.h"

#include "writer_impl.h"

namespace vispack::format {

using namespace detail;

void Writer::Impl::finish() {
  stop_workers();
  const std::uint64_t payload_end = pos;
  std::vector<std::uint32_t> label_ids;
  for (std::size_t k = 0; k < entries.size(); ++k) {
    if (!filled[k]) throw Error(cat(path, ": internal error: brick ", k, " was never written"));
    if (!entry_labels[k].empty()) {
      entries[k].label_first = std::uint32_t(label_ids.size());
      entries[k].label_count = std::uint32_t(entry_labels[k].size());
      label_ids.insert(label_ids.end(), entry_labels[k].begin(), entry_labels[k].end());
    }
  }
  std::string meta = metadata().dump();
  detail::FileHeader h{};
  std::memcpy(h.magic, detail::kMagic, 8);
  h.version_major = kFormatMajor;
  h.version_minor = kFormatMinor;
  h.header_size = detail::kHeaderSize;
  h.payload_offset = kPayloadAlignment;
  h.payload_end = payload_end;
  h.metadata_offset = payload_end;
  h.metadata_size = meta.size();
  h.index_offset = align_up(payload_end + meta.size(), 8);
  h.index_count = entries.size();
  h.labels_offset = h.index_offset + entries.size() * sizeof(IndexEntry);
  h.labels_count = label_ids.size();
  h.file_size = h.labels_offset + label_ids.size() * 4;
  h.index_entry_size = detail::kIndexEntrySize;
  h.brick_edge = std::uint32_t(opt.brick_edge);
  h.level_count = std::uint32_t(levels.size());
  h.channel_count = std::uint32_t(stored.size());

  XXH64_state_t* state = XXH64_createState();
  if (!state) throw std::bad_alloc();
  XXH64_reset(state, 0);
  XXH64_update(state, &h, detail::kChecksumFieldOffset);
  XXH64_update(state, meta.data(), meta.size());
  XXH64_update(state, zeros.data(), h.index_offset - (payload_end + meta.size()));
  XXH64_update(state, entries.data(), entries.size() * sizeof(IndexEntry));
  XXH64_update(state, label_ids.data(), label_ids.size() * 4);
  h.table_checksum = XXH64_digest(state);
  XXH64_freeState(state);

  file.write(meta);
  std::uint64_t pad = h.index_offset - (payload_end + meta.size());
  if (pad) file.write(zeros.data(), pad);
  file.write(entries.data(), entries.size() * sizeof(IndexEntry));
  file.write(label_ids.data(), label_ids.size() * 4);
  if (file.size() != h.file_size) {
    throw Error(
        cat(path, ": internal error: wrote ", file.size(), " bytes, expected ", h.file_size));
  }
  file.pwrite(&h, sizeof(h), 0);
  file.commit();
}

nlohmann::json Writer::Impl::metadata() const {
  VolumeMetadata meta;
  meta.dims = opt.dims;
  meta.spacing_mm = opt.spacing_mm;
  meta.origin_mm = opt.origin_mm;
  meta.brick_edge = opt.brick_edge;
  meta.channels = stored;
  meta.label_table = opt.label_table;
  meta.extra = opt.extra_metadata;
  return metadata_json(meta, geometry);
}

}  // namespace vispack::format

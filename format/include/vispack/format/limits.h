// Limits a packed file's header and metadata must respect (format/SPEC.md "Validation a reader
// must do"). Part of the format core: the reader refuses a file beyond them, and the writer
// refuses to make a file the reader would refuse. Plain values, no state.
#pragma once

#include <cstdint>

namespace vispack::format {

// Defaults suit any real volume; a caller may tighten them (a fuzzer, a small-memory viewer).
struct ReaderLimits {
  std::uint64_t max_metadata_bytes = std::uint64_t(64) << 20;  // JSON block
  std::uint64_t max_index_entries = std::uint64_t(1) << 26;    // bricks in the whole file
  std::uint64_t max_label_ids = std::uint64_t(1) << 28;        // label-set entries in total
  std::int64_t max_dim = (std::int64_t(1) << 31) - 1;          // voxels along one axis
  std::uint64_t max_level_voxels = std::uint64_t(1) << 48;     // product of one level's dims
};

}  // namespace vispack::format

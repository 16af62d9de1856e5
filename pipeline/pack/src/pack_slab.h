// The partial slab files of a sharded pack (format/SPEC.md "Partial slab files"): their layout,
// path and header, and the writer a shard uses. The merge's reader is in pack_merge.cpp.
// Private to pipeline/pack. Thread-safety: free functions; no shared state.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "pack_plan.h"
#include "vispack/format/writer.h"
#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline::detail {

inline constexpr char kSlabMagic[8] = {'\x89', 'V', 'P', 'S', '\r', '\n', '\x1a', '\n'};
inline constexpr std::size_t kSlabRecordSize = 48;
// 2: the slab's level-1 slices follow its bricks (the merge never decodes level 0).
// 3: the header records the body bounds of a cropped pack (crop_body_px), so the merge reads no
//    mask.
inline constexpr int kSlabVersion = 3;
inline constexpr int kSlabLevel1Zstd = 1;  // zstd level of the level-1 slices

// What a slab file holds: the slab's level-0 bricks (index order) and, per stored channel, its
// level-1 slices (format::encode_level0_slab) as one zstd frame with their raw size (none for a
// single-level volume).
struct SlabContent {
  std::vector<format::EncodedBrick> bricks;
  std::vector<std::vector<std::uint8_t>> level1;  // compressed
  std::vector<std::uint64_t> level1_raw;
};

// The output z range [first, last) of level-0 slab bz (output z = colour slot, pack_plan.h; the
// stack slices in it: stack_range_of_output_z).
std::pair<int, int> slab_slices(const PackPlan& plan, std::int64_t bz);

// What a slab is made from: its slices' intermediates, the palette (it decides the stored label
// type) and the geometry. A merge refuses a slab file whose recorded fingerprint differs.
std::string slab_input(const Config& config, const PackPlan& plan, std::int64_t bz);

// The header JSON of slab bz's file (`bricks`: their count; `input`: slab_input).
std::string slab_header_json(const PackPlan& plan, const std::vector<format::ChannelSpec>& stored,
                             std::int64_t bz, std::size_t bricks, const std::string& input);

// Writes the slab file at `path` atomically (AtomicFile), streamed with its running checksum.
void write_slab_file(const std::string& path, const std::string& header, const SlabContent& slab);

// WORK/pack-slabs/slab_NNNN.vpkslab.
std::string slab_path(const Config& config, std::int64_t bz);

}  // namespace vispack::pipeline::detail

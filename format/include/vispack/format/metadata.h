// The metadata JSON block of a packed file (format/SPEC.md "Metadata"): built by the writer,
// parsed and checked by the reader, both here so the two cannot drift apart.
// Pure functions, no state; safe to call from any thread.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "vispack/format/geometry.h"
#include "vispack/format/limits.h"
#include "vispack/format/types.h"

namespace vispack::format {

// What the metadata says about the volume (level 0; levels follow from make_geometry).
struct VolumeMetadata {
  std::array<std::int64_t, 3> dims{0, 0, 0};  // voxels along x, y, z
  std::array<double, 3> spacing_mm{1, 1, 1};  // mm, each > 0 and finite
  std::array<double, 3> origin_mm{0, 0, 0};   // mm, centre of voxel (0, 0, 0)
  int brick_edge = 0;
  std::vector<ChannelSpec> channels;  // stored types
  std::vector<LabelEntry> label_table;
  nlohmann::json extra = nlohmann::json::object();  // free-form "extra" object
};

// Maximum nesting depth of the metadata JSON a reader accepts.
inline constexpr int kMaxMetadataDepth = 64;

// "alpha_weighted_mean" (rgba8), "mean" (int16), "majority" (labels): the reduction rule of
// downsample.h that builds the pyramid of a channel of this type.
const char* downsample_rule(ChannelType type);

// The metadata object the vispack writer stores (keys of SPEC.md plus the informative
// "levels", "axes", "memory_order", "brick_padding"). Serialised with dump() it is
// byte-reproducible: the same input gives the same text.
nlohmann::json metadata_json(const VolumeMetadata& meta, const VolumeGeometry& geometry);

// Parses and checks `size` bytes of metadata JSON from the file `path` (for messages): nesting
// depth, every key the reader relies on, with types and ranges, and `limits` (max_dim,
// max_level_voxels). Stores the parsed document in `*root` when given. Throws FormatError
// "<path>: metadata key "<key>" <what>" (or "malformed metadata JSON", "nested deeper").
// Does not compare with the header: the caller checks brick_edge and the channel count.
VolumeMetadata parse_metadata(const std::string& path, const char* text, std::size_t size,
                              const ReaderLimits& limits, nlohmann::json* root = nullptr);

}  // namespace vispack::format

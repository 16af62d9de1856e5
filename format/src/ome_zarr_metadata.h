// The JSON documents of an OME-Zarr export (ome_zarr.h): Zarr v2 .zarray/.zgroup, Zarr v3
// zarr.json (array with the sharding codec, group), and the OME-NGFF attributes (multiscales,
// omero, labels, image-label) of versions 0.4 and 0.5. Pure functions; internal to
// vispack_format_export.
#pragma once

#include <nlohmann/json.hpp>

#include "ome_zarr_plan.h"
#include "vispack/format/reader.h"

namespace vispack::format::ome_zarr {

// The array shape of `image` at `level`: (z, y, x), with c = 3 first for kColour.
std::vector<std::int64_t> array_shape(const Reader& reader, const ExportImage& image, int level);

// The attributes of an image group: {"multiscales", "omero" (not for labels), "image-label"
// (labels)}. For 0.4 they are the .zattrs object; for 0.5 the object under "ome" (with
// "version"), see group_document().
nlohmann::json image_attributes(const Reader& reader, const ExportPlan& plan,
                                const ExportImage& image);
// The attributes of the "labels" group of plan.label_host: {"labels": [names]}.
nlohmann::json labels_group_attributes(const ExportPlan& plan);
// The attributes of the root group: {"vispack": {source file, images}} (no NGFF key).
nlohmann::json root_attributes(const Reader& reader, const ExportPlan& plan);

// Zarr v2 .zarray of `image` at `level`: chunks of one brick (3 x E^3 for colour), zstd.
nlohmann::json zarr_v2_array(const Reader& reader, const ExportImage& image, int level,
                             int zstd_level);
// Zarr v3 zarr.json of `image` at `level`: shards of shard_bricks^3 bricks, inner chunk =
// brick, codecs bytes + zstd, index bytes + crc32c at the end.
nlohmann::json zarr_v3_array(const Reader& reader, const ExportImage& image, int level,
                             int zstd_level, int shard_bricks);
// A Zarr v3 group zarr.json; `ngff_attributes` (may be null) go under attributes.ome with
// version "0.5"; `plain_attributes` (may be null) are merged into attributes as they are.
nlohmann::json zarr_v3_group(const nlohmann::json& ngff_attributes,
                             const nlohmann::json& plain_attributes);

}  // namespace vispack::format::ome_zarr

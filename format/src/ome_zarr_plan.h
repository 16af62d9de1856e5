// What an OME-Zarr export writes (ome_zarr.h): the images made from the packed file's channels,
// their paths, data types and fill values, and the levels. Internal to vispack_format_export.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "vispack/format/ome_zarr.h"
#include "vispack/format/reader.h"

namespace vispack::format::ome_zarr {

// Which part of a packed channel an image holds.
enum class ImageKind {
  kColour,  // r, g, b of an rgba8 channel: a channel axis of 3 before z
  kAlpha,   // component 3 (body coverage) of an rgba8 channel
  kScalar,  // an int16 channel (CT in HU)
  kLabels,  // a uint8/uint16 label channel, written as an NGFF image-label
};

struct ExportImage {
  std::string name;  // multiscale name ("rgb", "alpha", "ct", "labels")
  std::string path;  // group path under OUT, "/"-separated ("rgb/labels/labels")
  ImageKind kind = ImageKind::kScalar;
  int channel = 0;  // packed channel index
  ChannelType channel_type = ChannelType::kUint8;
  const char* dtype = "uint8";  // Zarr v3 data type name: "uint8", "int16", "uint16"
  std::size_t item_bytes = 1;   // bytes per array element
  int components = 1;           // length of the channel axis (3 for kColour, else no axis)
  // Fill value of every level's array: the most frequent value of the level-0 bricks that are
  // uniform (in every component, for colour), 0 when none is; bricks equal to it are skipped.
  std::int64_t fill_value = 0;
  bool label_has_source = false;  // kLabels under an image (image-label "source" = "../../")
};

struct ExportPlan {
  NgffVersion version = NgffVersion::k04;
  std::vector<int> levels;               // ascending
  std::vector<ExportImage> images;       // in write order; images of one channel are adjacent
  std::string label_host;                // path of the image that holds "labels/" (empty: none)
  std::vector<std::string> label_names;  // names listed in label_host/labels
};

// Resolves options.channels and options.levels against the file. Throws UsageError naming an
// unknown channel (and the channels the file has), a level outside the file's, or a repeated one.
ExportPlan make_export_plan(const Reader& reader, const OmeZarrOptions& options);

}  // namespace vispack::format::ome_zarr

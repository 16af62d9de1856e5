#include "ome_zarr_metadata.h"

#include <algorithm>
#include <cstdio>
#include <limits>

#include "vispack/format/metadata.h"

namespace vispack::format::ome_zarr {
namespace {

using nlohmann::json;

bool is_v04(const ExportPlan& plan) {
  return plan.version == NgffVersion::k04;
}

json axes_of(const ExportImage& image) {
  json axes = json::array();
  if (image.kind == ImageKind::kColour) axes.push_back({{"name", "c"}, {"type", "channel"}});
  for (const char* name : {"z", "y", "x"})
    axes.push_back({{"name", name}, {"type", "space"}, {"unit", "millimeter"}});
  return axes;
}

// One dataset: the level's path and its voxel-centre transform in mm, (c,) z, y, x order.
json dataset_of(const Reader& reader, const ExportImage& image, int level) {
  const LevelInfo& li = reader.level(level);
  json scale = json::array(), translation = json::array();
  if (image.kind == ImageKind::kColour) {
    scale.push_back(1.0);
    translation.push_back(0.0);
  }
  for (int axis = 2; axis >= 0; --axis) {
    scale.push_back(li.spacing_mm[std::size_t(axis)]);
    translation.push_back(li.origin_mm[std::size_t(axis)]);
  }
  return {{"path", std::to_string(level)},
          {"coordinateTransformations",
           json::array({{{"type", "scale"}, {"scale", scale}},
                        {{"type", "translation"}, {"translation", translation}}})}};
}

std::string hex_colour(const std::array<std::uint8_t, 3>& rgb) {
  char text[8];
  std::snprintf(text, sizeof text, "%02X%02X%02X", rgb[0], rgb[1], rgb[2]);
  return text;
}

json omero_channel(const std::string& label, const std::string& colour, double min, double max,
                   double start, double end) {
  return {{"label", label},
          {"color", colour},
          {"active", true},
          {"coefficient", 1},
          {"family", "linear"},
          {"inverted", false},
          {"window", {{"min", min}, {"max", max}, {"start", start}, {"end", end}}}};
}

// The value range of component `c` of a channel over its level-0 bricks (from the index).
std::pair<std::int64_t, std::int64_t> value_range(const Reader& reader, int channel, int c) {
  std::int64_t lo = std::numeric_limits<std::int64_t>::max();
  std::int64_t hi = std::numeric_limits<std::int64_t>::min();
  for (const BrickInfo& b : reader.bricks()) {
    if (b.level != 0 || b.channel != channel) continue;
    lo = std::min(lo, b.min[std::size_t(c)]);
    hi = std::max(hi, b.max[std::size_t(c)]);
  }
  return {lo, hi};
}

json omero_of(const Reader& reader, const ExportPlan& plan, const ExportImage& image) {
  json channels = json::array();
  json rdefs = {{"defaultT", 0}, {"defaultZ", reader.dims(0)[2] / 2}};
  switch (image.kind) {
    case ImageKind::kColour:
      channels.push_back(omero_channel("red", "FF0000", 0, 255, 0, 255));
      channels.push_back(omero_channel("green", "00FF00", 0, 255, 0, 255));
      channels.push_back(omero_channel("blue", "0000FF", 0, 255, 0, 255));
      rdefs["model"] = "color";
      break;
    case ImageKind::kAlpha:
      channels.push_back(omero_channel("alpha (body coverage)", "FFFFFF", 0, 255, 0, 255));
      rdefs["model"] = "greyscale";
      break;
    case ImageKind::kScalar: {
      // CT in HU: the soft-tissue window (width 400 HU, level 40 HU) within the data range.
      const auto [lo, hi] = value_range(reader, image.channel, 0);
      channels.push_back(
          omero_channel(image.name + " (HU)", "FFFFFF", double(lo), double(hi), -160.0, 240.0));
      rdefs["model"] = "greyscale";
      break;
    }
    case ImageKind::kLabels:
      break;
  }
  json omero = {{"name", image.name}, {"channels", channels}, {"rdefs", rdefs}};
  if (is_v04(plan)) omero["version"] = "0.4";
  return omero;
}

json image_label_of(const Reader& reader, const ExportPlan& plan, const ExportImage& image) {
  // Label 0 (unlabelled) is transparent; every label of the table gets its colour and name.
  json colours = json::array({{{"label-value", 0}, {"rgba", {0, 0, 0, 0}}}});
  json properties = json::array();
  for (const LabelEntry& e : reader.label_table()) {
    colours.push_back(
        {{"label-value", e.id}, {"rgba", {e.colour[0], e.colour[1], e.colour[2], 255}}});
    properties.push_back(
        {{"label-value", e.id}, {"name", e.name}, {"color", hex_colour(e.colour)}});
  }
  json label = {{"colors", colours}, {"properties", properties}};
  if (image.label_has_source) label["source"] = {{"image", "../../"}};
  if (is_v04(plan)) label["version"] = "0.4";
  return label;
}

std::string v2_dtype(const ExportImage& image) {
  if (image.item_bytes == 1) return "|u1";
  return image.channel_type == ChannelType::kInt16 ? "<i2" : "<u2";
}

std::vector<std::int64_t> chunk_shape(const Reader& reader, const ExportImage& image,
                                      std::int64_t bricks) {
  const std::int64_t e = reader.brick_edge() * bricks;
  std::vector<std::int64_t> shape;
  if (image.kind == ImageKind::kColour) shape.push_back(3);
  shape.insert(shape.end(), {e, e, e});
  return shape;
}

}  // namespace

std::vector<std::int64_t> array_shape(const Reader& reader, const ExportImage& image, int level) {
  const auto d = reader.dims(level);
  std::vector<std::int64_t> shape;
  if (image.kind == ImageKind::kColour) shape.push_back(3);
  shape.insert(shape.end(), {d[2], d[1], d[0]});
  return shape;
}

json image_attributes(const Reader& reader, const ExportPlan& plan, const ExportImage& image) {
  json datasets = json::array();
  for (int level : plan.levels)
    datasets.push_back(dataset_of(reader, image, level));
  json multiscale = {{"name", image.name},
                     {"axes", axes_of(image)},
                     {"datasets", datasets},
                     {"type", downsample_rule(image.channel_type)},
                     {"metadata",
                      {{"description",
                        "levels of a vispack packed volume: voxel i of level L+1 reduced from "
                        "voxels 2i and 2i+1 of level L on each axis (format/SPEC.md)"},
                       {"method", "vispack"}}}};
  if (is_v04(plan)) multiscale["version"] = "0.4";
  json attributes = {{"multiscales", json::array({multiscale})}};
  if (image.kind == ImageKind::kLabels) {
    attributes["image-label"] = image_label_of(reader, plan, image);
  } else {
    attributes["omero"] = omero_of(reader, plan, image);
  }
  return attributes;
}

json labels_group_attributes(const ExportPlan& plan) {
  return {{"labels", plan.label_names}};
}

json root_attributes(const Reader& reader, const ExportPlan& plan) {
  json images = json::array();
  for (const ExportImage& im : plan.images) {
    const char* kind = im.kind == ImageKind::kColour   ? "colour"
                       : im.kind == ImageKind::kAlpha  ? "alpha (body coverage)"
                       : im.kind == ImageKind::kLabels ? "labels"
                                                       : "scalar";
    images.push_back({{"path", im.path},
                      {"kind", kind},
                      {"channel", reader.channels()[std::size_t(im.channel)].name}});
  }
  return {{"vispack",
           {{"source", reader.path()},
            {"ngff", ngff_version_name(plan.version)},
            {"images", images},
            {"levels", plan.levels}}}};
}

json zarr_v2_array(const Reader& reader, const ExportImage& image, int level, int zstd_level) {
  return {{"zarr_format", 2},
          {"shape", array_shape(reader, image, level)},
          {"chunks", chunk_shape(reader, image, 1)},
          {"dtype", v2_dtype(image)},
          {"compressor", {{"id", "zstd"}, {"level", zstd_level}}},
          {"fill_value", image.fill_value},
          {"order", "C"},
          {"filters", nullptr},
          {"dimension_separator", "/"}};
}

json zarr_v3_array(const Reader& reader, const ExportImage& image, int level, int zstd_level,
                   int shard_bricks) {
  json names = json::array();
  if (image.kind == ImageKind::kColour) names.push_back("c");
  for (const char* n : {"z", "y", "x"})
    names.push_back(n);
  const json bytes = {{"name", "bytes"}, {"configuration", {{"endian", "little"}}}};
  json sharding = {
      {"name", "sharding_indexed"},
      {"configuration",
       {{"chunk_shape", chunk_shape(reader, image, 1)},
        {"codecs",
         json::array({bytes,
                      {{"name", "zstd"},
                       {"configuration", {{"level", zstd_level}, {"checksum", false}}}}})},
        {"index_codecs", json::array({bytes, {{"name", "crc32c"}}})},
        {"index_location", "end"}}}};
  return {{"zarr_format", 3},
          {"node_type", "array"},
          {"shape", array_shape(reader, image, level)},
          {"data_type", image.dtype},
          {"chunk_grid",
           {{"name", "regular"},
            {"configuration", {{"chunk_shape", chunk_shape(reader, image, shard_bricks)}}}}},
          {"chunk_key_encoding", {{"name", "default"}, {"configuration", {{"separator", "/"}}}}},
          {"fill_value", image.fill_value},
          {"codecs", json::array({sharding})},
          {"dimension_names", names},
          {"attributes", json::object()}};
}

json zarr_v3_group(const json& ngff_attributes, const json& plain_attributes) {
  json attributes = plain_attributes.is_object() ? plain_attributes : json::object();
  if (ngff_attributes.is_object()) {
    json ome = {{"version", "0.5"}};
    ome.update(ngff_attributes);
    attributes["ome"] = ome;
  }
  return {{"zarr_format", 3}, {"node_type", "group"}, {"attributes", attributes}};
}

}  // namespace vispack::format::ome_zarr

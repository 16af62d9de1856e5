#include "ome_zarr_plan.h"

#include <algorithm>
#include <map>

#include "vispack/common/error.h"

namespace vispack::format::ome_zarr {
namespace {

// The most frequent value among the uniform level-0 bricks of `channel` (for kColour: bricks
// whose r, g and b are one value; kAlpha: component 3), 0 when no brick qualifies. Ties go to
// the smaller value so the choice does not depend on map order.
std::int64_t most_common_uniform_value(const Reader& reader, int channel, ImageKind kind) {
  std::map<std::int64_t, std::uint64_t> counts;
  const LevelInfo& level = reader.level(0);
  for (std::int64_t bz = 0; bz < level.bricks[2]; ++bz) {
    for (std::int64_t by = 0; by < level.bricks[1]; ++by) {
      for (std::int64_t bx = 0; bx < level.bricks[0]; ++bx) {
        const BrickInfo& b = reader.brick(channel, 0, bx, by, bz);
        if (kind == ImageKind::kColour) {
          bool one = true;
          for (int c = 0; c < 3; ++c)
            one = one && b.min[c] == b.max[c] && b.min[c] == b.min[0];
          if (one) ++counts[b.min[0]];
        } else {
          const int c = kind == ImageKind::kAlpha ? 3 : 0;
          if (b.min[c] == b.max[c]) ++counts[b.min[c]];
        }
      }
    }
  }
  std::int64_t best = 0;
  std::uint64_t best_count = 0;
  for (const auto& [value, count] : counts) {
    if (count > best_count) best = value, best_count = count;
  }
  return best;
}

ExportImage image_of(const Reader& reader, int channel, ImageKind kind, std::string name) {
  ExportImage im;
  im.name = name;
  im.path = std::move(name);
  im.kind = kind;
  im.channel = channel;
  im.channel_type = reader.channels()[std::size_t(channel)].type;
  switch (im.channel_type) {
    case ChannelType::kRgba8:
    case ChannelType::kUint8:
      im.dtype = "uint8", im.item_bytes = 1;
      break;
    case ChannelType::kInt16:
      im.dtype = "int16", im.item_bytes = 2;
      break;
    case ChannelType::kUint16:
      im.dtype = "uint16", im.item_bytes = 2;
      break;
  }
  im.components = kind == ImageKind::kColour ? 3 : 1;
  im.fill_value = most_common_uniform_value(reader, channel, kind);
  return im;
}

std::vector<int> selected_channels(const Reader& reader, const OmeZarrOptions& options) {
  std::vector<int> out;
  if (options.channels.empty()) {
    for (int c = 0; c < int(reader.channels().size()); ++c)
      out.push_back(c);
    return out;
  }
  for (const std::string& name : options.channels) {
    const auto c = reader.find_channel(name);
    if (!c) {
      std::string names;
      for (const auto& s : reader.channels())
        names += (names.empty() ? "" : ", ") + s.name;
      throw UsageError(
          cat(reader.path(), ": no channel \"", name, "\" (the file has: ", names, ")"));
    }
    if (std::find(out.begin(), out.end(), *c) != out.end())
      throw UsageError(cat("--channels names \"", name, "\" twice"));
    out.push_back(*c);
  }
  return out;
}

std::vector<int> selected_levels(const Reader& reader, const OmeZarrOptions& options) {
  std::vector<int> levels = options.levels;
  if (levels.empty()) {
    for (int l = 0; l < reader.level_count(); ++l)
      levels.push_back(l);
  }
  std::sort(levels.begin(), levels.end());
  for (std::size_t i = 0; i < levels.size(); ++i) {
    if (levels[i] < 0 || levels[i] >= reader.level_count()) {
      throw UsageError(cat("--levels: level ", levels[i], " is outside [0, ",
                           reader.level_count() - 1, "] for ", reader.path()));
    }
    if (i > 0 && levels[i] == levels[i - 1])
      throw UsageError(cat("--levels names level ", levels[i], " twice"));
  }
  return levels;
}

}  // namespace

ExportPlan make_export_plan(const Reader& reader, const OmeZarrOptions& options) {
  ExportPlan plan;
  plan.version = options.version;
  plan.levels = selected_levels(reader, options);
  std::vector<int> label_channels;
  for (int c : selected_channels(reader, options)) {
    const ChannelSpec& spec = reader.channels()[std::size_t(c)];
    if (spec.type == ChannelType::kRgba8) {
      const bool plain = spec.name == "rgba";
      plan.images.push_back(
          image_of(reader, c, ImageKind::kColour, plain ? "rgb" : spec.name + "_rgb"));
      plan.images.push_back(
          image_of(reader, c, ImageKind::kAlpha, plain ? "alpha" : spec.name + "_alpha"));
    } else if (spec.type == ChannelType::kInt16) {
      plan.images.push_back(image_of(reader, c, ImageKind::kScalar, spec.name));
    } else {
      label_channels.push_back(c);
    }
  }
  // Labels hang under the first image (the colour one when there is one: it comes first).
  if (!plan.images.empty()) plan.label_host = plan.images.front().path;
  for (int c : label_channels) {
    const std::string& name = reader.channels()[std::size_t(c)].name;
    ExportImage im = image_of(reader, c, ImageKind::kLabels, name);
    if (!plan.label_host.empty()) {
      im.path = plan.label_host + "/labels/" + name;
      im.label_has_source = true;
      plan.label_names.push_back(name);
    }
    plan.images.push_back(std::move(im));
  }
  // Two images may not share a path (a channel called "rgb" beside one called "rgba"...).
  for (std::size_t i = 0; i < plan.images.size(); ++i) {
    for (std::size_t j = 0; j < i; ++j) {
      if (plan.images[i].path == plan.images[j].path) {
        throw UsageError(cat(reader.path(), ": two exported images would both be called \"",
                             plan.images[i].path,
                             "\"; export one of their channels with --channels"));
      }
    }
  }
  return plan;
}

}  // namespace vispack::format::ome_zarr

#include "vispack/format/summary.h"

#include <limits>

namespace vispack::format {
namespace {

ChannelSummary channel_summary(const Reader& r, int c) {
  ChannelSummary s;
  const ChannelSpec& spec = r.channels()[std::size_t(c)];
  s.name = spec.name;
  s.type = spec.type;
  const int comps = channel_type_components(spec.type);
  s.min.assign(std::size_t(comps), std::numeric_limits<std::int64_t>::max());
  s.max.assign(std::size_t(comps), std::numeric_limits<std::int64_t>::min());
  const bool labels = is_label_type(spec.type);
  std::vector<bool> ids(labels ? 65536 : 0, false);
  for (const BrickInfo& b : r.bricks()) {
    if (b.channel != c) continue;
    ++s.bricks;
    switch (b.codec) {
      case Codec::kUniform:
        ++s.uniform_bricks;
        break;
      case Codec::kRaw:
        ++s.raw_bricks;
        break;
      case Codec::kZstd:
        ++s.zstd_bricks;
        break;
    }
    s.stored_bytes += b.stored_size;
    if (b.level != 0) continue;
    for (int k = 0; k < comps; ++k) {
      s.min[std::size_t(k)] = std::min(s.min[std::size_t(k)], b.min[std::size_t(k)]);
      s.max[std::size_t(k)] = std::max(s.max[std::size_t(k)], b.max[std::size_t(k)]);
    }
    if (labels) {
      for (std::uint32_t id : r.brick_labels(b))
        ids[id] = true;
    }
  }
  const auto d = r.dims(0);
  s.level0_raw_bytes = std::uint64_t(d[0]) * std::uint64_t(d[1]) * std::uint64_t(d[2]) *
                       channel_type_bytes(spec.type);
  if (labels) {
    std::uint64_t n = 0;
    for (bool b : ids)
      n += b;
    s.distinct_labels = n;
  }
  return s;
}

}  // namespace

Summary summarize(const Reader& reader, const SummaryOptions& options) {
  Summary s;
  s.file = reader.path();
  s.version_major = reader.version_major();
  s.version_minor = reader.version_minor();
  s.file_size = reader.file_size();
  s.brick_edge = reader.brick_edge();
  s.brick_count = reader.bricks().size();
  for (int l = 0; l < reader.level_count(); ++l)
    s.levels.push_back(reader.level(l));
  for (int c = 0; c < int(reader.channels().size()); ++c)
    s.channels.push_back(channel_summary(reader, c));
  s.label_table_size = reader.label_table().size();
  s.metadata = reader.metadata();
  if (options.verify) {
    s.verified = true;
    s.findings = reader.check(options.deep, options.threads);
  }
  return s;
}

nlohmann::json to_json(const Finding& f) {
  nlohmann::json j = {{"finding", f.number()},
                      {"title", defect_title(f.kind)},
                      {"detail", f.detail},
                      {"text", f.text()}};
  if (f.has_brick) {
    j["level"] = f.level;
    j["channel"] = f.channel_name;
    j["brick"] = f.brick;
  }
  return j;
}

nlohmann::json to_json(const Summary& s) {
  nlohmann::json out = {{"file", s.file},
                        {"version", {s.version_major, s.version_minor}},
                        {"file_size", s.file_size},
                        {"brick_edge", s.brick_edge}};
  nlohmann::json levels = nlohmann::json::array();
  for (const LevelInfo& li : s.levels) {
    levels.push_back({{"dims", li.dims},
                      {"bricks", li.bricks},
                      {"spacing_mm", li.spacing_mm},
                      {"origin_mm", li.origin_mm}});
  }
  out["levels"] = levels;
  nlohmann::json channels = nlohmann::json::array();
  for (const ChannelSummary& c : s.channels) {
    nlohmann::json j = {{"name", c.name},
                        {"type", channel_type_name(c.type)},
                        {"bricks", c.bricks},
                        {"uniform_bricks", c.uniform_bricks},
                        {"raw_bricks", c.raw_bricks},
                        {"zstd_bricks", c.zstd_bricks},
                        {"stored_bytes", c.stored_bytes},
                        {"level0_raw_bytes", c.level0_raw_bytes},
                        {"min", c.min},
                        {"max", c.max}};
    if (c.distinct_labels) j["distinct_labels"] = *c.distinct_labels;
    channels.push_back(std::move(j));
  }
  out["channels"] = channels;
  out["metadata"] = s.metadata;
  if (s.verified) {
    nlohmann::json findings = nlohmann::json::array();
    for (const Finding& f : s.findings)
      findings.push_back(to_json(f));
    out["verify"] = {{"ok", s.findings.empty()}, {"findings", findings}};
  }
  return out;
}

}  // namespace vispack::format

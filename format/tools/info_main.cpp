// vispack-info FILE [--json] [--verify [--deep]]: a packed volume's metadata, sizes and stats.
#include <cstdio>
#include <iostream>
#include <limits>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/format/reader.h"

using namespace vispack;
using namespace vispack::format;

namespace {

// Per-channel summary over the index: codec counts, stored bytes, level-0 value range.
nlohmann::json channel_summary(const Reader& r, int c) {
  std::uint64_t counts[3] = {0, 0, 0}, stored = 0, bricks = 0;
  const int comps = channel_type_components(r.channels()[std::size_t(c)].type);
  std::vector<std::int64_t> lo(comps, std::numeric_limits<std::int64_t>::max());
  std::vector<std::int64_t> hi(comps, std::numeric_limits<std::int64_t>::min());
  std::vector<bool> ids(65536, false);
  for (const BrickInfo& b : r.bricks()) {
    if (b.channel != c) continue;
    ++bricks;
    ++counts[int(b.codec)];
    stored += b.stored_size;
    if (b.level != 0) continue;
    for (int k = 0; k < comps; ++k) {
      lo[k] = std::min(lo[k], b.min[k]);
      hi[k] = std::max(hi[k], b.max[k]);
    }
    for (std::uint32_t id : r.brick_labels(b))
      ids[id] = true;
  }
  const auto d = r.dims(0);
  const std::uint64_t raw =
      std::uint64_t(d[0]) * d[1] * d[2] * channel_type_bytes(r.channels()[std::size_t(c)].type);
  nlohmann::json j = {{"name", r.channels()[std::size_t(c)].name},
                      {"type", channel_type_name(r.channels()[std::size_t(c)].type)},
                      {"bricks", bricks},
                      {"uniform_bricks", counts[0]},
                      {"raw_bricks", counts[1]},
                      {"zstd_bricks", counts[2]},
                      {"stored_bytes", stored},
                      {"level0_raw_bytes", raw},
                      {"min", lo},
                      {"max", hi}};
  if (is_label_type(r.channels()[std::size_t(c)].type)) {
    std::uint64_t n = 0;
    for (bool b : ids)
      n += b;
    j["distinct_labels"] = n;
  }
  return j;
}

}  // namespace

int main(int argc, char** argv) {
  return run_main("vispack-info", argc, argv, [](Args& args) {
    args.describe(
        "FILE [--json] [--verify [--deep]]",
        "Prints a packed volume's metadata, sizes and per-channel statistics. With --verify, "
        "checks every brick checksum and that all padding is zero; the first bad brick is "
        "named (level, channel, brick x/y/z) and the exit code is 4.");
    const bool json = args.flag("--json", "print one JSON object instead of text");
    const bool verify = args.flag("--verify", "check every checksum and the zero padding");
    const bool deep =
        args.flag("--deep", "with --verify: also decode every brick and check its stats");
    const std::string file = args.positional("FILE", "packed volume (.vpk)");
    args.done();

    Reader r = Reader::open(file);
    nlohmann::json out = {{"file", file},
                          {"version", {r.version_major(), r.version_minor()}},
                          {"file_size", r.file_size()},
                          {"brick_edge", r.brick_edge()}};
    nlohmann::json levels = nlohmann::json::array();
    for (int l = 0; l < r.level_count(); ++l) {
      const LevelInfo& li = r.level(l);
      levels.push_back({{"dims", li.dims},
                        {"bricks", li.bricks},
                        {"spacing_mm", li.spacing_mm},
                        {"origin_mm", li.origin_mm}});
    }
    out["levels"] = levels;
    nlohmann::json channels = nlohmann::json::array();
    for (int c = 0; c < int(r.channels().size()); ++c)
      channels.push_back(channel_summary(r, c));
    out["channels"] = channels;
    out["metadata"] = r.metadata();

    VerifyResult v;
    if (verify) {
      v = r.verify(deep);
      out["verify"] = {{"ok", v.ok}, {"message", v.message}};
      if (v.brick) {
        out["verify"]["brick"] = {{"level", v.brick->level},
                                  {"channel", r.channels()[std::size_t(v.brick->channel)].name},
                                  {"brick", v.brick->brick}};
      }
    }
    if (json) {
      std::cout << out.dump(2) << "\n";
    } else {
      const auto d = r.dims(0);
      const auto s = r.spacing_mm(0);
      const auto o = r.origin_mm(0);
      std::printf("file:        %s\n", file.c_str());
      std::printf("version:     %u.%u\n", r.version_major(), r.version_minor());
      std::printf("size:        %llu bytes\n", (unsigned long long)r.file_size());
      std::printf("dims:        %lld x %lld x %lld voxels\n", (long long)d[0], (long long)d[1],
                  (long long)d[2]);
      std::printf("spacing:     %g x %g x %g mm\n", s[0], s[1], s[2]);
      std::printf("origin:      %g, %g, %g mm\n", o[0], o[1], o[2]);
      std::printf("bricks:      edge %d, %zu in all\n", r.brick_edge(), r.bricks().size());
      for (int l = 0; l < r.level_count(); ++l) {
        const LevelInfo& li = r.level(l);
        std::printf("level %-2d     %lld x %lld x %lld voxels, %lld x %lld x %lld bricks\n", l,
                    (long long)li.dims[0], (long long)li.dims[1], (long long)li.dims[2],
                    (long long)li.bricks[0], (long long)li.bricks[1], (long long)li.bricks[2]);
      }
      for (const auto& c : channels) {
        const double raw = c["level0_raw_bytes"].get<double>();
        std::printf(
            "channel %-8s %-6s %llu bytes stored (all levels; level 0 raw %llu, ratio %.2f), "
            "bricks %llu uniform / %llu raw / %llu zstd, level-0 range %s .. %s",
            c["name"].get<std::string>().c_str(), c["type"].get<std::string>().c_str(),
            (unsigned long long)c["stored_bytes"].get<std::uint64_t>(),
            (unsigned long long)c["level0_raw_bytes"].get<std::uint64_t>(),
            c["stored_bytes"].get<double>() > 0 ? raw / c["stored_bytes"].get<double>() : 0.0,
            (unsigned long long)c["uniform_bricks"].get<std::uint64_t>(),
            (unsigned long long)c["raw_bricks"].get<std::uint64_t>(),
            (unsigned long long)c["zstd_bricks"].get<std::uint64_t>(), c["min"].dump().c_str(),
            c["max"].dump().c_str());
        if (c.contains("distinct_labels")) {
          std::printf(", %llu distinct labels",
                      (unsigned long long)c["distinct_labels"].get<std::uint64_t>());
        }
        std::printf("\n");
      }
      std::printf("label table: %zu entries\n", r.label_table().size());
      const auto& extra = r.metadata().value("extra", nlohmann::json::object());
      if (!extra.empty()) std::printf("extra:       %s\n", extra.dump().c_str());
      if (verify) std::printf("verify:      %s\n", v.ok ? "ok" : v.message.c_str());
    }
    if (verify && !v.ok) throw FormatError(v.message);
    return 0;
  });
}

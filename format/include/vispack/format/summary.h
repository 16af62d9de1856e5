// What vispack-info shows about a packed file, computed by the reader library so any tool (or a
// test) gets the same numbers: geometry, per-channel brick counts, stored bytes and level-0
// value ranges from the index, and, on request, the verifier's findings.
// summarize() only reads the Reader (const; safe beside other readers of the same Reader).
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "vispack/format/findings.h"
#include "vispack/format/reader.h"

namespace vispack::format {

struct ChannelSummary {
  std::string name;
  ChannelType type = ChannelType::kUint8;
  std::uint64_t bricks = 0;          // over all levels
  std::uint64_t uniform_bricks = 0;  // codec counts, all levels
  std::uint64_t raw_bricks = 0;
  std::uint64_t zstd_bricks = 0;
  std::uint64_t stored_bytes = 0;                // payload bytes, all levels
  std::uint64_t level0_raw_bytes = 0;            // dims product * bytes per voxel
  std::vector<std::int64_t> min, max;            // per component, over level 0 (from the index)
  std::optional<std::uint64_t> distinct_labels;  // label channels: IDs present in level 0
};

struct Summary {
  std::string file;  // the path as given to Reader::open
  std::uint16_t version_major = 0, version_minor = 0;
  std::uint64_t file_size = 0;  // bytes
  int brick_edge = 0;
  std::uint64_t brick_count = 0;  // index entries
  std::vector<LevelInfo> levels;
  std::vector<ChannelSummary> channels;
  std::size_t label_table_size = 0;
  nlohmann::json metadata;  // the whole metadata block
  bool verified = false;    // check() ran; `findings` holds its result
  std::vector<Finding> findings;
};

struct SummaryOptions {
  bool verify = false;  // run Reader::check()
  bool deep = false;    // with verify: decode every brick and compare its stats
  int threads = 0;      // for check(); 0 = resolve_threads()
};

Summary summarize(const Reader& reader, const SummaryOptions& options = {});

// The --json form: {"file", "version", "file_size", "brick_edge", "levels", "channels",
// "metadata"} and, when verified, "verify": {"ok", "findings": [{"finding", "title", "level",
// "channel", "brick", "detail", "text"}]} ("level", "channel", "brick" only when a brick is
// named).
nlohmann::json to_json(const Summary& summary);
nlohmann::json to_json(const Finding& finding);

}  // namespace vispack::format

// vispack-info FILE [--json] [--verify [--deep]]: a packed volume's metadata, sizes and stats.
// A screen over format::summarize(); the findings of --verify are numbered (FINDINGS.md).
#include <cstdio>
#include <iostream>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/common/exit_codes.h"
#include "vispack/format/reader.h"
#include "vispack/format/summary.h"

using namespace vispack;
using namespace vispack::format;

namespace {

const char* kProgram = "vispack-info";

std::string values(const std::vector<std::int64_t>& v) {
  return nlohmann::json(v).dump();
}

std::string readable(const nlohmann::json& v, int depth);

// Integers as ascending ranges: "0..127", "1001..1499, 1501..2871"; at most `max_runs` runs
// (then how many in all). The list is shown in its own order; runs break where it steps by not 1.
std::string ranges(const nlohmann::json& list, std::size_t max_runs = 6) {
  std::string out;
  std::size_t runs = 0, i = 0;
  const std::size_t n = list.size();
  while (i < n) {
    std::size_t j = i;
    while (j + 1 < n && list[j + 1].get<std::int64_t>() == list[j].get<std::int64_t>() + 1)
      ++j;
    if (runs < max_runs) {
      out += runs ? ", " : "";
      out += std::to_string(list[i].get<std::int64_t>());
      if (j > i) out += ".." + std::to_string(list[j].get<std::int64_t>());
    }
    ++runs;
    i = j + 1;
  }
  if (runs > max_runs) out += vispack::cat(", ... (", runs, " runs)");
  return out;
}

bool all_integers(const nlohmann::json& list) {
  for (const auto& v : list)
    if (!v.is_number_integer() && !v.is_number_unsigned()) return false;
  return true;
}

// A JSON value in a few words: objects as "key value, ...", lists of integers as their count and
// ranges, long lists of anything else as their count; nested objects in parentheses. Lines are
// cut at 200 characters ("..."; --json prints everything).
std::string readable(const nlohmann::json& v, int depth) {
  std::string out;
  if (v.is_object()) {
    if (v.empty()) return "none";
    for (auto it = v.begin(); it != v.end(); ++it) {
      out += out.empty() ? "" : ", ";
      const std::string inner = readable(it.value(), depth + 1);
      out += it.key() + " " +
             (it.value().is_object() && !it.value().empty() ? "(" + inner + ")" : inner);
    }
  } else if (v.is_array()) {
    if (v.empty()) return "none";
    if (all_integers(v))
      out = v.size() == 1 ? ranges(v) : vispack::cat(v.size(), ": ", ranges(v));
    else if (v.size() <= 4)
      out = v.dump();
    else
      out = vispack::cat(v.size(), " entries");
  } else if (v.is_string()) {
    out = v.get<std::string>().empty() ? "-" : v.get<std::string>();
  } else if (v.is_number_float()) {
    char text[32];
    std::snprintf(text, sizeof text, "%.4g", v.get<double>());
    out = text;
  } else if (v.is_null()) {
    out = "none";
  } else {
    out = v.dump();
  }
  if (depth == 0 && out.size() > 200) out = out.substr(0, 197) + "...";
  return out;
}

void print_text(const Summary& s) {
  const LevelInfo& l0 = s.levels.front();
  std::printf("file:        %s\n", s.file.c_str());
  std::printf("version:     %u.%u\n", s.version_major, s.version_minor);
  std::printf("size:        %llu bytes\n", (unsigned long long)s.file_size);
  std::printf("dims:        %lld x %lld x %lld voxels\n", (long long)l0.dims[0],
              (long long)l0.dims[1], (long long)l0.dims[2]);
  std::printf("spacing:     %g x %g x %g mm\n", l0.spacing_mm[0], l0.spacing_mm[1],
              l0.spacing_mm[2]);
  std::printf("origin:      %g, %g, %g mm\n", l0.origin_mm[0], l0.origin_mm[1], l0.origin_mm[2]);
  std::printf("bricks:      edge %d, %llu in all\n", s.brick_edge,
              (unsigned long long)s.brick_count);
  for (std::size_t l = 0; l < s.levels.size(); ++l) {
    const LevelInfo& li = s.levels[l];
    std::printf("level %-2zu     %lld x %lld x %lld voxels, %lld x %lld x %lld bricks\n", l,
                (long long)li.dims[0], (long long)li.dims[1], (long long)li.dims[2],
                (long long)li.bricks[0], (long long)li.bricks[1], (long long)li.bricks[2]);
  }
  for (const ChannelSummary& c : s.channels) {
    const double ratio =
        c.stored_bytes > 0 ? double(c.level0_raw_bytes) / double(c.stored_bytes) : 0.0;
    std::printf(
        "channel %-8s %-6s %llu bytes stored (all levels; level 0 raw %llu, ratio %.2f), "
        "bricks %llu uniform / %llu raw / %llu zstd, level-0 range %s .. %s",
        c.name.c_str(), channel_type_name(c.type), (unsigned long long)c.stored_bytes,
        (unsigned long long)c.level0_raw_bytes, ratio, (unsigned long long)c.uniform_bricks,
        (unsigned long long)c.raw_bricks, (unsigned long long)c.zstd_bricks, values(c.min).c_str(),
        values(c.max).c_str());
    if (c.distinct_labels)
      std::printf(", %llu distinct labels", (unsigned long long)*c.distinct_labels);
    std::printf("\n");
  }
  std::printf("label table: %zu entries\n", s.label_table_size);
  // The writer's free-form metadata ("extra"; a packed volume's slice numbers, registration,
  // provenance): one line per key, integer lists as ranges. --json prints all of it as it is.
  const auto& extra = s.metadata.value("extra", nlohmann::json::object());
  if (extra.is_object()) {
    for (auto it = extra.begin(); it != extra.end(); ++it) {
      const std::string key = it.key() + ":";
      std::printf("%-12s %s\n", key.c_str(), readable(it.value(), 0).c_str());
    }
  } else if (!extra.is_null()) {
    std::printf("extra:       %s\n", readable(extra, 0).c_str());
  }
  if (s.verified) {
    if (s.findings.empty())
      std::printf("verify:      ok\n");
    else
      std::printf("verify:      %zu finding%s\n", s.findings.size(),
                  s.findings.size() == 1 ? "" : "s");
  }
}

// One stderr line per finding: "vispack-info: finding N: <where><detail>".
void print_findings(const std::vector<Finding>& findings) {
  std::fflush(stdout);
  for (const Finding& f : findings)
    std::fprintf(stderr, "%s: %s\n", kProgram, f.text().c_str());
}

}  // namespace

int main(int argc, char** argv) {
  return run_main(kProgram, argc, argv, [](Args& args) {
    args.describe(
        "FILE [--json] [--verify [--deep]]",
        "Prints a short summary of a packed volume: geometry, levels, bricks, per-channel sizes "
        "and value ranges, the label table, and the writer's metadata one line per key (slice "
        "numbers as ranges); --json prints everything, the whole metadata included. With --verify, "
        "checks the file and prints one numbered finding per defect to stderr, e.g. "
        "\"vispack-info: finding 8: level 0 channel ct brick (1,0,2): payload checksum "
        "mismatch (...)\" (numbers: format/FINDINGS.md); the exit code is 4 when there is any.");
    const bool json = args.flag("--json", "print one JSON object instead of text");
    const bool verify = args.flag("--verify", "check every checksum and the zero padding");
    const bool deep =
        args.flag("--deep", "with --verify: also decode every brick and check its stats");
    const std::string file = args.positional("FILE", "packed volume (.vpk)");
    args.done();

    std::optional<Reader> reader;
    try {
      reader.emplace(Reader::open(file));
    } catch (const FileDefect& e) {
      if (!verify) throw;
      // A structural defect: nothing after it can be trusted, so it is the only finding.
      if (json) {
        nlohmann::json out = {{"file", file},
                              {"verify", {{"ok", false}, {"findings", {to_json(e.finding())}}}}};
        std::cout << out.dump(2) << "\n";
      }
      print_findings({e.finding()});
      return int(ExitCode::kInvalidFile);
    }
    SummaryOptions options;
    options.verify = verify;
    options.deep = deep;
    const Summary s = summarize(*reader, options);
    if (json)
      std::cout << to_json(s).dump(2) << "\n";
    else
      print_text(s);
    std::cout.flush();
    print_findings(s.findings);
    return s.findings.empty() ? 0 : int(ExitCode::kInvalidFile);
  });
}

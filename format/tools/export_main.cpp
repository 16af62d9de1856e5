// vispack-export FILE.vpk --ome-zarr OUT.zarr [--ngff 0.4|0.5] [--channels A,B] [--levels L]
#include <cstdio>
#include <sstream>
#include <string>
#include <vector>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/format/ome_zarr.h"
#include "vispack/format/reader.h"

using namespace vispack;
using namespace vispack::format;

namespace {

std::vector<std::string> split_list(const std::string& text, const std::string& option) {
  std::vector<std::string> items;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ','))
    items.push_back(item);
  if (items.empty() || text.back() == ',') items.push_back("");
  for (const auto& i : items)
    if (i.empty()) throw UsageError(cat(option, " \"", text, "\" has an empty item"));
  return items;
}

int parse_level(const std::string& text, const std::string& whole) {
  std::size_t used = 0;
  int value = -1;
  try {
    value = std::stoi(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  if (used != text.size() || text.empty() || value < 0)
    throw UsageError(cat("--levels \"", whole, "\": \"", text, "\" is not a level number"));
  return value;
}

// "0,2,3", "1-3" or a mix; every level once.
std::vector<int> parse_levels(const std::string& text) {
  std::vector<int> levels;
  for (const std::string& item : split_list(text, "--levels")) {
    const auto dash = item.find('-');
    if (dash == std::string::npos) {
      levels.push_back(parse_level(item, text));
      continue;
    }
    const int a = parse_level(item.substr(0, dash), text);
    const int b = parse_level(item.substr(dash + 1), text);
    if (b < a) throw UsageError(cat("--levels \"", text, "\": range ", item, " is empty"));
    for (int l = a; l <= b; ++l)
      levels.push_back(l);
  }
  return levels;
}

}  // namespace

int main(int argc, char** argv) {
  return run_main("vispack-export", argc, argv, [](Args& args) {
    args.describe(
        "FILE.vpk --ome-zarr OUT.zarr [--ngff 0.4|0.5] [--channels A,B] [--levels L]",
        "Writes a packed volume as OME-Zarr (OME-NGFF), which napari, neuroglancer, Fiji "
        "(BigDataViewer, MoBIE) and web viewers open: each level one dataset of a multiscale "
        "image with scale and translation in mm; colour (c = r, g, b), alpha (body coverage) "
        "and CT (int16 HU) as images, label channels as image-labels with the label table's "
        "names and colours. One chunk per brick (zstd; fill-value bricks not written). "
        "NGFF 0.4 is Zarr v2 (one file per chunk); 0.5 is Zarr v3 with sharding (one file per "
        "shard). Written under OUT.zarr.partial-XXXXXX and renamed at the end. "
        "docs/OME_ZARR.md describes the layout.");
    const std::string out =
        args.option("--ome-zarr", "OUT", "output folder (OME-Zarr), e.g. body.zarr").value_or("");
    const std::string version =
        args.option("--ngff", "V", "NGFF version: 0.4 (Zarr v2) or 0.5 (Zarr v3, sharded)", "0.4");
    const auto channels = args.option("--channels", "A,B",
                                      "packed channels to export (default: all), e.g. rgba,labels");
    const auto levels =
        args.option("--levels", "L", "levels to export (default: all), e.g. 0-2 or 0,3");
    const auto zstd_level = args.option_int("--zstd-level", "N",
                                            "zstd level of encoded chunks "
                                            "(default 3)");
    const auto shard = args.option_int("--shard-bricks", "S",
                                       "0.5: bricks per shard edge, a shard holds S^3 (default 8)");
    const auto threads = args.option_int("--threads", "N", "encoder threads (default: all cores)");
    const bool no_copy = args.flag(
        "--no-copy", "re-encode every chunk instead of copying stored zstd bricks (to measure)");
    const bool overwrite = args.flag("--overwrite", "replace OUT once the new export is complete");
    const bool quiet = args.flag("--quiet", "no progress output");
    const std::string file = args.positional("FILE.vpk", "packed volume (.vpk)");
    args.done();
    if (out.empty()) throw UsageError("--ome-zarr OUT is required");

    OmeZarrOptions options;
    options.version = parse_ngff_version(version);
    if (channels) options.channels = split_list(*channels, "--channels");
    if (levels) options.levels = parse_levels(*levels);
    if (zstd_level) options.zstd_level = int(*zstd_level);
    if (shard) options.shard_bricks = int(*shard);
    if (threads) {
      if (*threads < 1) throw UsageError(cat("--threads ", *threads, " must be at least 1"));
      options.threads = int(*threads);
    }
    options.copy_stored_bricks = !no_copy;
    options.overwrite = overwrite;
    options.quiet = quiet;

    const Reader reader = Reader::open(file);
    const OmeZarrStats s = export_ome_zarr(reader, out, options);
    std::printf(
        "%s: NGFF %s, %llu bricks: %llu chunks copied, %llu encoded, %llu fill (not written); "
        "%llu files (%llu shards), %llu bytes, %.2f s\n",
        out.c_str(), ngff_version_name(options.version), (unsigned long long)s.bricks,
        (unsigned long long)s.chunks_copied, (unsigned long long)s.chunks_encoded,
        (unsigned long long)s.chunks_skipped, (unsigned long long)s.files,
        (unsigned long long)s.shards, (unsigned long long)s.bytes, s.seconds);
    return 0;
  });
}

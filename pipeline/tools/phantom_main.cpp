// vispack-phantom: writes a synthetic slice folder with ground truth (DESIGN.md section 5).
#include <algorithm>
#include <cstdio>
#include <iostream>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/phantom.h"

int main(int argc, char** argv) {
  return vispack::run_main("vispack-phantom", argc, argv, [](vispack::Args& args) {
    args.describe(
        "--out DIR [--preset tiny|small|medium|vhp] [--seed N] [--slices N] [--rgb-raw] "
        "[--seg-jpeg] [--defects|--no-defects] [--threads N] [--quiet]",
        "Writes a synthetic Visible-Human-style slice folder (rgb/, ct/, seg/, palette.json,\n"
        "config.json) with ground truth in truth/ (NRRD volumes and transforms.json).\n"
        "The same options give a byte-identical folder.");
    const auto out = args.option("--out", "DIR", "output folder (created if missing)");
    const std::string preset =
        args.option("--preset", "NAME", "tiny | small | medium | vhp", "small");
    const auto seed = args.option_int("--seed", "N", "random seed (default 1)");
    const auto slices =
        args.option_int("--slices", "N", "number of slices (default: the preset's)");
    vispack::pipeline::PhantomOptions options;
    options.rgb_raw =
        args.flag("--rgb-raw", "colour slices as header-less planar .raw (NLM style)");
    options.seg_jpeg = args.flag("--seg-jpeg", "segmentation as JPEG (quality 90: noisy colours)");
    const bool defects = args.flag("--defects", "add one black and one duplicated slice");
    const bool no_defects = args.flag("--no-defects", "no black or duplicated slice");
    const auto threads = args.option_int("--threads", "N", "worker threads (default: all cores)");
    options.quiet = args.flag("--quiet", "no progress output");
    args.done();
    if (!out || out->empty()) throw vispack::UsageError("--out DIR is required");
    if (defects && no_defects) throw vispack::UsageError("--defects and --no-defects conflict");
    if (seed && *seed < 0) throw vispack::UsageError("--seed must not be negative");
    if (threads && *threads < 0) throw vispack::UsageError("--threads must not be negative");
    options.preset = preset;
    options.seed = seed ? static_cast<std::uint64_t>(*seed) : 1;
    options.slices = slices ? static_cast<int>(std::clamp<long long>(*slices, -1, 1 << 30)) : 0;
    if (slices && *slices <= 0) throw vispack::UsageError("--slices must be at least 2");
    if (defects) options.defects = true;
    if (no_defects) options.defects = false;
    options.threads = threads ? static_cast<int>(*threads) : 0;
    const auto summary = vispack::pipeline::make_phantom(*out, options);
    std::printf("%s: %dx%dx%d RGB, %dx%d CT, jump at slice %d", out->c_str(), summary.width,
                summary.height, summary.slices, summary.ct_size, summary.ct_size,
                summary.jump_slice);
    if (summary.black_slice >= 0) {
      std::printf(", black slice %d, duplicate slice %d", summary.black_slice,
                  summary.duplicate_slice);
    }
    std::printf(" (%.2f s)\n", summary.seconds);
    return 0;
  });
}

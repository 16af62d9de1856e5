// vispack-phantom: writes a synthetic slice folder with ground truth (docs/GOALS.md §5):
// an analytic preset (phantom.h) or colour slices synthesised from a real CT (from_ct.h).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <string>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/phantom/from_ct.h"
#include "vispack/phantom/phantom.h"

int main(int argc, char** argv) {
  return vispack::run_main("vispack-phantom", argc, argv, [](vispack::Args& args) {
    args.describe(
        "--out DIR [--preset NAME | --from-ct CT [--first K] [--margin PX]] [--ct-scale F] [--seed "
        "N] [--slices N] "
        "[--rgb-raw] [--seg-jpeg] [--defects|--no-defects] [--fiducials|--no-fiducials] "
        "[--ct-every N] [--seg-every N] [--no-drift] [--drift MODEL] [--no-jump] [--jump-px "
        "MIN:MAX] "
        "[--threads N] [--quiet]",
        "Writes a synthetic Visible-Human-style slice folder (rgb/, ct/, seg/, palette.json,\n"
        "config.json) with ground truth in truth/ (NRRD volumes and transforms.json).\n"
        "--from-ct synthesises the colour slices from a real CT (a .nrrd, a config.json, or a\n"
        "sample folder such as data/samples/head-ct) instead of the analytic body.\n"
        "The same options give a byte-identical folder.");
    const auto out = args.option("--out", "DIR", "output folder (created if missing)");
    const auto preset = args.option(
        "--preset", "NAME",
        "tiny | small | medium | vhp | anatomy | anatomy-vhp | male | male-small (default small)");
    const auto from_ct = args.option("--from-ct", "CT", "synthesise from this real CT volume");
    const auto first =
        args.option_int("--first", "K", "--from-ct: first CT slice (default: centred)");
    const auto ct_scale = args.option_double(
        "--ct-scale", "F",
        "CT pixel / colour pixel (--from-ct: an integer, default 2; presets: the preset's)");
    const auto ct_every = args.option_int(
        "--ct-every", "N",
        "a CT slice only at every Nth colour slice (ct.slice_spacing_mm); --from-ct: the colour\n"
        "      N times finer along z than the CT, synthesised from the CT interpolated along z");
    const auto seg_every = args.option_int(
        "--seg-every", "N",
        "presets: a segmentation slice only at every Nth colour slice (seg.slice_spacing_mm)");
    const auto margin =
        args.option_int("--margin", "PX", "--from-ct: gel around the CT's field of view, px");
    const auto seed = args.option_int("--seed", "N", "random seed (default 1)");
    const auto slices = args.option_int("--slices", "N",
                                        "number of slices (default: the preset's / all CT slices)");
    vispack::phantom::PhantomOptions options;
    options.rgb_raw =
        args.flag("--rgb-raw", "colour slices as header-less planar .raw (NLM style)");
    options.seg_jpeg = args.flag("--seg-jpeg", "segmentation as JPEG (quality 90: noisy colours)");
    const bool defects = args.flag("--defects", "add one black and one duplicated slice");
    const bool no_defects = args.flag("--no-defects", "no black or duplicated slice");
    const bool fiducials = args.flag("--fiducials", "draw the two fiducial tubes");
    const bool no_fiducials = args.flag("--no-fiducials", "no fiducial tubes");
    const bool no_drift = args.flag("--no-drift", "true drift exactly zero (camera offset stays)");
    const auto drift_model = args.option(
        "--drift", "MODEL",
        "presets: walk (default: the Gaussian walk the solver's prior assumes) | heavy\n"
        "      (heavy-tailed steps) | rotation (plus 0.02 deg/slice) | bowed (a bowed stack)");
    const bool no_jump = args.flag("--no-jump", "no block jump");
    const auto jump_px = args.option(
        "--jump-px", "MIN:MAX", "presets: block jump magnitude in px (default 10:15; 7:9 tiny)");
    const auto threads =
        args.option_int("--threads", "N", "threads in all, this one included (default: all cores)");
    const bool quiet = args.flag("--quiet", "no progress output");
    args.done();
    if (!out || out->empty()) throw vispack::UsageError("--out DIR is required");
    if (defects && no_defects) throw vispack::UsageError("--defects and --no-defects conflict");
    if (fiducials && no_fiducials)
      throw vispack::UsageError("--fiducials and --no-fiducials conflict");
    if (seed && *seed < 0) throw vispack::UsageError("--seed must not be negative");
    if (threads && *threads < 0) throw vispack::UsageError("--threads must not be negative");
    if (slices && *slices <= 0) throw vispack::UsageError("--slices must be at least 2");
    const std::uint64_t seed_value = seed ? static_cast<std::uint64_t>(*seed) : 1;
    const int slice_count =
        slices ? static_cast<int>(std::clamp<long long>(*slices, -1, 1 << 30)) : 0;
    const int thread_count = threads ? static_cast<int>(*threads) : 0;

    if (from_ct) {
      if (preset) throw vispack::UsageError("--preset and --from-ct conflict");
      if (drift_model || jump_px)
        throw vispack::UsageError("--drift and --jump-px apply to the presets only");
      if (seg_every) throw vispack::UsageError("--seg-every applies to the presets only");
      if (options.rgb_raw || options.seg_jpeg || defects || fiducials)
        throw vispack::UsageError(
            "--rgb-raw, --seg-jpeg, --defects and --fiducials apply to the presets only");
      vispack::phantom::FromCtOptions o;
      o.seed = seed_value;
      o.slices = slice_count;
      o.first = first ? static_cast<int>(std::clamp<long long>(*first, -1, 1 << 30)) : -1;
      if (ct_every) o.ct_every = static_cast<int>(std::clamp<long long>(*ct_every, -1, 1 << 20));
      if (first && *first < 0) throw vispack::UsageError("--first must not be negative");
      if (ct_scale && *ct_scale != std::floor(*ct_scale))
        throw vispack::UsageError("--ct-scale must be an integer with --from-ct");
      o.scale = ct_scale ? static_cast<int>(std::clamp(*ct_scale, 0.0, 100.0)) : 2;
      if (margin && *margin < 0) throw vispack::UsageError("--margin must not be negative");
      if (margin) o.margin_px = static_cast<int>(std::min<long long>(*margin, 1 << 20));
      o.drift = !no_drift;
      o.jump = !no_jump;
      o.threads = thread_count;
      o.quiet = quiet;
      const auto ct = vispack::phantom::read_ct_volume(*from_ct);
      const auto s = vispack::phantom::make_phantom_from_ct(*out, ct, o);
      std::printf(
          "%s: %dx%dx%d RGB from CT slices %d..%d (%dx%d), jump at slice %d, body %.1f %% "
          "(%.2f s)\n",
          out->c_str(), s.width, s.height, s.slices, s.first_ct_slice,
          s.first_ct_slice + s.slices - 1, s.ct_width, s.ct_height, s.jump_slice,
          100.0 * s.body_fraction, s.seconds);
      return 0;
    }
    if (first || margin) throw vispack::UsageError("--first and --margin need --from-ct");
    if (drift_model) options.drift_model = vispack::phantom::parse_drift_model(*drift_model);
    if (jump_px) {
      const auto colon = jump_px->find(':');
      char* end = nullptr;
      const double lo = std::strtod(jump_px->c_str(), &end);
      const bool lo_ok = colon != std::string::npos && end == jump_px->c_str() + colon;
      const double hi = lo_ok ? std::strtod(jump_px->c_str() + colon + 1, &end) : 0.0;
      if (!lo_ok || *end != '\0' || colon + 1 == jump_px->size())
        throw vispack::UsageError("--jump-px '" + *jump_px + "': expected MIN:MAX in px, e.g. 3:6");
      options.jump_px_min = lo;
      options.jump_px_max = hi;
    }
    if (ct_every)
      options.ct_every = static_cast<int>(std::clamp<long long>(*ct_every, -1, 1 << 20));
    if (seg_every)
      options.seg_every = static_cast<int>(std::clamp<long long>(*seg_every, -1, 1 << 20));
    if (ct_scale) options.ct_scale = *ct_scale;
    options.preset = preset.value_or("small");
    options.seed = seed_value;
    options.slices = slice_count;
    if (defects) options.defects = true;
    if (no_defects) options.defects = false;
    if (fiducials) options.fiducials = true;
    if (no_fiducials) options.fiducials = false;
    if (no_drift) options.drift = false;
    if (no_jump) options.jump = false;
    options.threads = thread_count;
    options.quiet = quiet;
    const auto summary = vispack::phantom::make_phantom(*out, options);
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

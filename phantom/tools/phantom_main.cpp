// vispack-phantom: writes a synthetic slice folder with ground truth (docs/GOALS.md §5):
// an analytic preset (phantom.h) or colour slices synthesised from a real CT (from_ct.h).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <optional>
#include <string>
#include <tuple>
#include <utility>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/phantom/from_ct.h"
#include "vispack/phantom/phantom.h"

namespace {

// The command line as given (each option unset when absent).
struct PhantomArgs {
  std::optional<std::string> out, preset, from_ct, drift_model, jump_px;
  std::optional<long long> first, ct_every, seg_every, margin, seed, slices, threads, blocks,
      black_slices, truth_every;
  std::optional<double> ct_scale, keep_free_gb;
  bool rgb_raw = false, seg_jpeg = false, defects = false, no_defects = false, fiducials = false,
       no_fiducials = false, no_drift = false, no_jump = false, quiet = false;
  // Checked and clamped: the seed (default 1), the slice count (0: the default), the threads.
  std::uint64_t seed_value = 1;
  int slice_count = 0, thread_count = 0;
};

// Declares every option (in --help's order), parses them and checks what holds for both kinds.
PhantomArgs parse(vispack::Args& args) {
  args.describe(
      "--out DIR [--preset NAME | --from-ct CT [--first K] [--margin PX]] [--ct-scale F] [--seed "
      "N] [--slices N] "
      "[--rgb-raw] [--seg-jpeg] [--defects|--no-defects] [--fiducials|--no-fiducials] "
      "[--ct-every N] [--seg-every N] [--no-drift] [--drift MODEL] [--no-jump] [--jump-px "
      "MIN:MAX] "
      "[--blocks N] [--black-slices N] [--truth-every K] [--keep-free-gb GB] [--threads N] "
      "[--quiet]",
      "Writes a synthetic Visible-Human-style slice folder (rgb/, ct/, seg/, palette.json,\n"
      "config.json) with ground truth in truth/ (NRRD volumes and transforms.json).\n"
      "--from-ct synthesises the colour slices from a real CT (a .nrrd, a config.json, or a\n"
      "sample folder such as data/samples/head-ct) instead of the analytic body.\n"
      "The same options give a byte-identical folder.");
  PhantomArgs a;
  a.out = args.option("--out", "DIR", "output folder (created if missing)");
  a.preset = args.option(
      "--preset", "NAME",
      "tiny | small | medium | vhp | anatomy | anatomy-vhp | male | korean | male-small\n"
      "      (default small)");
  a.from_ct = args.option("--from-ct", "CT", "synthesise from this real CT volume");
  a.first = args.option_int("--first", "K", "--from-ct: first CT slice (default: centred)");
  a.ct_scale = args.option_double(
      "--ct-scale", "F",
      "CT pixel / colour pixel (--from-ct: an integer, default 2; presets: the preset's)");
  a.ct_every = args.option_int(
      "--ct-every", "N",
      "a CT slice only at every Nth colour slice (ct.slice_spacing_mm); --from-ct: the colour\n"
      "      N times finer along z than the CT, synthesised from the CT interpolated along z");
  a.seg_every = args.option_int(
      "--seg-every", "N",
      "presets: a segmentation slice only at every Nth colour slice (seg.slice_spacing_mm)");
  a.margin = args.option_int("--margin", "PX", "--from-ct: gel around the CT's field of view, px");
  a.seed = args.option_int("--seed", "N", "random seed (default 1)");
  a.slices =
      args.option_int("--slices", "N", "number of slices (default: the preset's / all CT slices)");
  a.rgb_raw = args.flag("--rgb-raw", "colour slices as header-less planar .raw (NLM style)");
  a.seg_jpeg = args.flag("--seg-jpeg", "segmentation as JPEG (quality 90: noisy colours)");
  a.defects = args.flag("--defects", "add one black and one duplicated slice");
  a.no_defects = args.flag("--no-defects", "no black or duplicated slice");
  a.fiducials = args.flag("--fiducials", "draw the two fiducial tubes");
  a.no_fiducials = args.flag("--no-fiducials", "no fiducial tubes");
  a.no_drift = args.flag("--no-drift", "true drift exactly zero (camera offset stays)");
  a.drift_model = args.option(
      "--drift", "MODEL",
      "presets: walk (default: the Gaussian walk the solver's prior assumes) | heavy\n"
      "      (heavy-tailed steps) | rotation (plus 0.02 deg/slice) | bowed (a bowed stack)");
  a.no_jump = args.flag("--no-jump", "no block jump");
  a.jump_px = args.option("--jump-px", "MIN:MAX",
                          "presets: block jump magnitude in px (default 10:15; 7:9 tiny)");
  a.blocks = args.option_int(
      "--blocks", "N",
      "presets: N blocks of equal length, a block jump at each boundary and a brightness\n"
      "      step per block (the VH male: 4)");
  a.black_slices =
      args.option_int("--black-slices", "N", "presets: N black slices spread over the stack");
  a.truth_every = args.option_int(
      "--truth-every", "K",
      "presets: a streamed folder: no truth volumes, only truth/sample/ mask and labels PNGs\n"
      "      of every Kth slice (memory independent of the slice count)");
  a.keep_free_gb = args.option_double(
      "--keep-free-gb", "GB",
      "fail before writing when the folder would leave less than GB free (default 0)");
  a.threads =
      args.option_int("--threads", "N", "threads in all, this one included (default: all cores)");
  a.quiet = args.flag("--quiet", "no progress output");
  args.done();
  if (!a.out || a.out->empty()) throw vispack::UsageError("--out DIR is required");
  if (a.defects && a.no_defects) throw vispack::UsageError("--defects and --no-defects conflict");
  if (a.fiducials && a.no_fiducials)
    throw vispack::UsageError("--fiducials and --no-fiducials conflict");
  if (a.seed && *a.seed < 0) throw vispack::UsageError("--seed must not be negative");
  if (a.threads && *a.threads < 0) throw vispack::UsageError("--threads must not be negative");
  if (a.slices && *a.slices <= 0) throw vispack::UsageError("--slices must be at least 2");
  a.seed_value = a.seed ? static_cast<std::uint64_t>(*a.seed) : 1;
  a.slice_count = a.slices ? static_cast<int>(std::clamp<long long>(*a.slices, -1, 1 << 30)) : 0;
  a.thread_count = a.threads ? static_cast<int>(*a.threads) : 0;
  return a;
}

// --from-ct: colour synthesised from a real CT.
int run_from_ct(const PhantomArgs& a) {
  if (a.preset) throw vispack::UsageError("--preset and --from-ct conflict");
  if (a.drift_model || a.jump_px)
    throw vispack::UsageError("--drift and --jump-px apply to the presets only");
  if (a.seg_every) throw vispack::UsageError("--seg-every applies to the presets only");
  if (a.rgb_raw || a.seg_jpeg || a.defects || a.fiducials)
    throw vispack::UsageError(
        "--rgb-raw, --seg-jpeg, --defects and --fiducials apply to the presets only");
  if (a.blocks || a.black_slices || a.truth_every || a.keep_free_gb)
    throw vispack::UsageError(
        "--blocks, --black-slices, --truth-every and --keep-free-gb apply to the presets only");
  vispack::phantom::FromCtOptions o;
  o.seed = a.seed_value;
  o.slices = a.slice_count;
  o.first = a.first ? static_cast<int>(std::clamp<long long>(*a.first, -1, 1 << 30)) : -1;
  if (a.ct_every) o.ct_every = static_cast<int>(std::clamp<long long>(*a.ct_every, -1, 1 << 20));
  if (a.first && *a.first < 0) throw vispack::UsageError("--first must not be negative");
  if (a.ct_scale && *a.ct_scale != std::floor(*a.ct_scale))
    throw vispack::UsageError("--ct-scale must be an integer with --from-ct");
  o.scale = a.ct_scale ? static_cast<int>(std::clamp(*a.ct_scale, 0.0, 100.0)) : 2;
  if (a.margin && *a.margin < 0) throw vispack::UsageError("--margin must not be negative");
  if (a.margin) o.margin_px = static_cast<int>(std::min<long long>(*a.margin, 1 << 20));
  o.drift = !a.no_drift;
  o.jump = !a.no_jump;
  o.threads = a.thread_count;
  o.quiet = a.quiet;
  const auto ct = vispack::phantom::read_ct_volume(*a.from_ct);
  const auto s = vispack::phantom::make_phantom_from_ct(*a.out, ct, o);
  std::printf(
      "%s: %dx%dx%d RGB from CT slices %d..%d (%dx%d), jump at slice %d, body %.1f %% "
      "(%.2f s)\n",
      a.out->c_str(), s.width, s.height, s.slices, s.first_ct_slice,
      s.first_ct_slice + s.slices - 1, s.ct_width, s.ct_height, s.jump_slice,
      100.0 * s.body_fraction, s.seconds);
  return 0;
}

// --jump-px MIN:MAX as two numbers (px).
std::pair<double, double> parse_jump_px(const std::string& text) {
  const auto colon = text.find(':');
  char* end = nullptr;
  const double lo = std::strtod(text.c_str(), &end);
  const bool lo_ok = colon != std::string::npos && end == text.c_str() + colon;
  const double hi = lo_ok ? std::strtod(text.c_str() + colon + 1, &end) : 0.0;
  if (!lo_ok || *end != '\0' || colon + 1 == text.size())
    throw vispack::UsageError("--jump-px '" + text + "': expected MIN:MAX in px, e.g. 3:6");
  return {lo, hi};
}

// An analytic preset.
int run_preset(const PhantomArgs& a) {
  if (a.first || a.margin) throw vispack::UsageError("--first and --margin need --from-ct");
  vispack::phantom::PhantomOptions options;
  options.rgb_raw = a.rgb_raw;
  options.seg_jpeg = a.seg_jpeg;
  if (a.ct_every)
    options.ct_every = static_cast<int>(std::clamp<long long>(*a.ct_every, -1, 1 << 20));
  if (a.seg_every)
    options.seg_every = static_cast<int>(std::clamp<long long>(*a.seg_every, -1, 1 << 20));
  if (a.ct_scale) options.ct_scale = *a.ct_scale;
  options.preset = a.preset.value_or("small");
  options.seed = a.seed_value;
  options.slices = a.slice_count;
  if (a.defects) options.defects = true;
  if (a.no_defects) options.defects = false;
  if (a.fiducials) options.fiducials = true;
  if (a.no_fiducials) options.fiducials = false;
  if (a.no_drift) options.drift = false;
  if (a.no_jump) options.jump = false;
  if (a.drift_model) options.drift_model = vispack::phantom::parse_drift_model(*a.drift_model);
  if (a.jump_px) std::tie(options.jump_px_min, options.jump_px_max) = parse_jump_px(*a.jump_px);
  auto clamp_int = [](long long v) {
    return static_cast<int>(std::clamp<long long>(v, -1, 1 << 30));
  };
  if (a.blocks) options.blocks = clamp_int(*a.blocks);
  if (a.black_slices) options.black_slices = clamp_int(*a.black_slices);
  if (a.truth_every) options.truth_every = clamp_int(*a.truth_every);
  if (a.keep_free_gb) {
    if (!(*a.keep_free_gb >= 0 && *a.keep_free_gb < 1e9))
      throw vispack::UsageError("--keep-free-gb must be a number of GB, 0 or more");
    options.keep_free_bytes = static_cast<std::uint64_t>(*a.keep_free_gb * 1e9);
  }
  options.threads = a.thread_count;
  options.quiet = a.quiet;
  const auto summary = vispack::phantom::make_phantom(*a.out, options);
  std::printf("%s: %dx%dx%d RGB, %dx%d CT, jump at slice %d", a.out->c_str(), summary.width,
              summary.height, summary.slices, summary.ct_size, summary.ct_size, summary.jump_slice);
  if (summary.black_slice >= 0) {
    std::printf(", black slice %d, duplicate slice %d", summary.black_slice,
                summary.duplicate_slice);
  }
  if (summary.jump_slices.size() > 1) std::printf(", %zu block jumps", summary.jump_slices.size());
  if (summary.black_slices.size() > 1)
    std::printf(", %zu black slices", summary.black_slices.size());
  if (!summary.truth_sample.empty())
    std::printf(", truth of %zu slices in truth/sample", summary.truth_sample.size());
  std::printf(" (%.2f s)\n", summary.seconds);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  return vispack::run_main("vispack-phantom", argc, argv, [](vispack::Args& args) {
    const PhantomArgs a = parse(args);
    return a.from_ct ? run_from_ct(a) : run_preset(a);
  });
}

// The vispack-register stage driver: per-slice records (pairs + CT anchor, sharded), the global
// solve, registered slices and QC pictures. See register_stage.h for how shards combine.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <utility>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/common/progress.h"
#include "vispack/pipeline/core/layout_check.h"
#include "vispack/pipeline/core/output_frame.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/intermediates.h"
#include "vispack/pipeline/imaging/opencv_threads.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/register.h"
#include "vispack/pipeline/register/register_stage.h"

namespace vispack::pipeline {
namespace {

namespace fs = std::filesystem;

constexpr int kOverlayEdge = 512;  // longer edge of the QC overlay, px
// The CT body fraction of the working grid under which estimate_ct_anchor finds nothing to anchor
// on (ct_anchor.cpp): the report's "no body in the CT".
constexpr double kAnchorMinBody = 1e-3;

// `slice` (8/16-bit grey or RGB) as 8-bit RGB with its longer edge at most `max_edge` (INTER_AREA):
// the picture the overlay draws on.
cv::Mat overlay_picture(const cv::Mat& slice, int max_edge) {
  cv::Mat out = shrink_to_edge(slice, max_edge);
  if (out.depth() == CV_16U) out.convertTo(out, CV_8U, 255.0 / 65535.0);
  if (out.channels() == 1) cv::cvtColor(out, out, cv::COLOR_GRAY2RGB);
  return out;
}

// `picture` (an overlay_picture of a slice on a `grid`-sized stack) registered by `rigid`: the
// warp registered_colour applies at full size, carried to the picture's pixel grid.
cv::Mat warp_picture(const cv::Mat& picture, const Rigid& rigid, cv::Size grid) {
  const double sx = double(picture.cols) / grid.width, sy = double(picture.rows) / grid.height;
  const cv::Matx23d small_to_full{1.0 / sx, 0, 0.5 / sx - 0.5, 0, 1.0 / sy, 0.5 / sy - 0.5};
  const cv::Matx23d full_to_small{sx, 0, 0.5 * sx - 0.5, 0, sy, 0.5 * sy - 0.5};
  const cv::Matx23d m = compose_affine(
      full_to_small, compose_affine(rigid_matrix(rigid, image_centre(grid)), small_to_full));
  cv::Mat out;
  cv::warpAffine(picture, out, cv::Mat(m), picture.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                 cv::BORDER_REPLICATE);
  return out;
}

std::string pairs_path(const Config& config, int k) {
  return slice_output_path(config, "register", "pairs/pairs", k, "json");
}

// The overlay picture of slice k (overlay_picture, lossless PNG), written with its pair record
// as the slice is read for it: the run that later draws the slice's QC overlay (after the solve:
// the same run, or a later shard in another process) warps it instead of decoding and warping
// the full-size slice again (~0.1 s a slice at 2048x1216), and no run holds the pictures of its
// range in memory between the two (docs/BENCHMARKS.md "Memory as the work grows, per stage").
// The record holds the picture's identity ("picture"), so a picture that is not the one written
// with the record is never used.
std::string picture_path(const Config& config, int k) {
  return slice_output_path(config, "register", "pairs/picture", k, "png");
}

// The overlay picture of slice k recorded with its pair record, or an empty matrix.
cv::Mat recorded_picture(const Config& config, int k) {
  try {
    const auto record = nlohmann::json::parse(read_file(pairs_path(config, k)));
    const std::string identity = record.value("picture", "");
    const std::string path = picture_path(config, k);
    if (identity.empty() || file_identity(path) != identity) return {};
    return read_slice(path);
  } catch (const std::exception&) {
    return {};  // no record or no picture: the caller decodes the slice
  }
}

// Fingerprint of what the record of slice k depends on: the register config section, the
// anchor's inputs (ct section, output frame, hu threshold) and the files k−4..k (+ the CT slices
// at slice k's z, slice_z.h).
std::string pair_fingerprint(const Config& config, const std::vector<SliceFile>& files,
                             const std::vector<SliceFile>& ct_files, bool anchored, int k) {
  Fingerprint fp;
  // The record's layout and method version (v4: σ from the body size; v5: every body part in the
  // anchor, its part counts recorded; v6: the anchor's CT body keeps elongated soft tissue).
  fp.text("pairs-v6");
  fp.text(config_section_hash(config, {"register", "spacing_mm"}));
  for (int j = std::max(0, k - 4); j <= k; ++j)
    fp.file(files[std::size_t(j)].path);
  if (anchored) {
    fp.text(config_section_hash(config, {"ct", "mask.hu_threshold", "mask.min_part_mm2"}));
    const CtAtZ at = ct_at_colour_slice(config, int(ct_files.size()), files[std::size_t(k)].slot);
    const SliceFile* ct = at.inside() ? &ct_files[std::size_t(at.below)] : nullptr;
    fp.text(ct ? ct->path : "no CT slice");
    if (ct) fp.file(ct->path);
    if (at.inside() && !at.exact())
      fp.number(at.w_above).file(ct_files[std::size_t(at.above)].path);
  }
  return fp.str();
}

// The stored record of slice k if it exists and is current.
std::optional<SlicePairs> load_pairs(const std::string& path, const std::string& fingerprint) {
  std::error_code ec;
  if (!fs::exists(path, ec)) return std::nullopt;
  try {
    auto j = nlohmann::json::parse(read_file(path, 1 << 20));
    if (j.value("fingerprint", "") != fingerprint) return std::nullopt;
    return slice_pairs_from_json(j, path);
  } catch (const std::exception&) {
    return std::nullopt;  // unreadable or stale: recomputed
  }
}

void warn(const StageOptions& options, const std::string& message) {
  (void)options;  // warnings are printed even with --quiet: they change what the output means
  std::fprintf(stderr, "vispack-register: warning: %s\n", message.c_str());
}

// What the steps of one register run share: its inputs, options and StageRun, the records'
// fingerprints and the bytes read.
struct RegisterRun {
  RegisterRun(const Config& config_, const StageOptions& options_,
              const std::vector<SliceFile>& files_, const RegisterOptions& reg_, bool anchored_,
              const std::vector<SliceFile>& ct_files_, const std::vector<SliceOverride>& overrides_,
              const std::vector<std::string>& z_warnings_, StageRun& run_)
      : config(config_),
        options(options_),
        files(files_),
        n(int(files_.size())),
        reg(reg_),
        anchored(anchored_),
        ct_files(ct_files_),
        overrides(overrides_),
        z_warnings(z_warnings_),
        run(run_),
        range(run_.range()),
        tpath(transforms_path(config_)) {}

  const Config& config;
  const StageOptions& options;
  const std::vector<SliceFile>& files;  // the colour stack
  const int n;
  const RegisterOptions& reg;  // config.registration, method "none" when disabled
  const bool anchored;         // CT anchors measured and used
  const std::vector<SliceFile>& ct_files;
  const std::vector<SliceOverride>& overrides;
  const std::vector<std::string>& z_warnings;  // printed when the stage began
  StageRun& run;
  const SliceRange range;
  const std::string tpath;  // <work>/register/transforms.json
  std::optional<Similarity> ct_to_rgb;
  AnchorOptions anchor_options;
  std::vector<std::string> fingerprints;
  std::atomic<std::uint64_t> bytes{0};

  const std::string& fingerprint(int k) {
    std::string& f = fingerprints[std::size_t(k)];
    if (f.empty()) f = pair_fingerprint(config, files, ct_files, anchored, k);
    return f;
  }
};

// Slice k read for its records (its size checked against the stack's), its overlay picture
// written (picture_path), prepared for registration.
RegisterFrame read_frame(RegisterRun& r, int k, cv::Size stack_size, double anchor_scale) {
  const auto& files = r.files;
  cv::Mat slice = read_slice(files[std::size_t(k)].path, r.config.rgb.raw);
  if (slice.size() != stack_size)
    throw InputError(cat(files[std::size_t(k)].path, ": slice is ", slice.cols, "x", slice.rows,
                         ", the stack (", files[0].path, ") is ", stack_size.width, "x",
                         stack_size.height));
  r.bytes += slice.total() * slice.elemSize();
  if (k >= r.range.first && k < r.range.last)
    write_work_image(picture_path(r.config, k), overlay_picture(slice, kOverlayEdge));
  return prepare_frame(slice, r.reg, anchor_scale);
}

// Slice k's CT anchor: none outside the CT's z range; between two CT slices (slice_z.h) the
// nearest one, trusted less the farther it lies, or the CT interpolated to slice k's z
// (register.ct_anchor_between).
std::optional<AnchorEstimate> anchor_of(RegisterRun& r, int k, const RegisterFrame& f) {
  const Config& config = r.config;
  const CtAtZ at = ct_at_colour_slice(config, int(r.ct_files.size()), r.files[std::size_t(k)].slot);
  if (!at.inside()) return std::nullopt;
  const bool nearest = !at.exact() && r.reg.ct_anchor_between == "nearest";
  const cv::Mat hu = nearest
                         ? read_ct_hu(*config.ct, r.ct_files[std::size_t(at.nearest())].path)
                         : ct_hu_at_colour_slice(config, r.ct_files, r.files[std::size_t(k)].slot);
  r.bytes += hu.total() * 2;
  AnchorEstimate est = estimate_ct_anchor(f, hu, *r.ct_to_rgb, r.anchor_options);
  if (nearest) {
    est.confidence *= std::max(0.0, 1.0 - 2.0 * at.distance_mm / ct_slice_spacing_mm(config));
    est.ok = est.ok && est.confidence > 0.0;
  }
  return est;
}

// 1. The per-slice records (pairs + CT anchor) of the range that are missing or stale, written
// to <work>/register/pairs/. Returns how many were computed.
int measure_records(RegisterRun& r) {
  const Config& config = r.config;
  const SliceRange range = r.range;
  make_directories(r.run.dir() + "/pairs");
  int first_missing = range.last, last_missing = range.first - 1;
  for (int k = range.first; k < range.last; ++k) {
    if (r.options.force || !load_pairs(pairs_path(config, k), r.fingerprint(k))) {
      first_missing = std::min(first_missing, k);
      last_missing = std::max(last_missing, k);
    }
  }
  if (first_missing > last_missing) return 0;
  // Every slice must have the first slice's size (a slice replaced between runs).
  const cv::Size stack_size = read_slice_size(r.files[0].path, config.rgb.raw);
  const double anchor_scale = r.anchored ? anchor_working_scale(config) : 0.0;
  auto frame = [&](int k) { return read_frame(r, k, stack_size, anchor_scale); };
  std::function<std::optional<AnchorEstimate>(int, const RegisterFrame&)> anchor;
  if (r.anchored && r.reg.method != "none")
    anchor = [&](int k, const RegisterFrame& f) { return anchor_of(r, k, f); };
  std::vector<SlicePairs> computed =
      compute_pairs(first_missing, last_missing + 1, frame, r.reg, r.run.threads(), anchor);
  for (const auto& p : computed) {
    nlohmann::json j = to_json(p);
    j["fingerprint"] = r.fingerprint(p.index);
    if (range.contains(p.index)) j["picture"] = file_identity(picture_path(config, p.index));
    write_file_atomic(pairs_path(config, p.index), j.dump(1) + "\n");
  }
  return int(computed.size());
}

// The anchor mode the solve uses: "ct" when anchored, "none" without registration or when
// asked, else "fiducials" ("fiducials", or "auto" without CT).
std::string solve_anchor_mode(const RegisterRun& r) {
  if (r.anchored) return "ct";
  if (r.reg.anchor == "none" || !r.reg.enabled) return "none";
  return "fiducials";
}

// transforms.json, rewritten only on change. Compared in memory: shards that solve at the same
// time (each register run that finds every record solves: on a cluster every per-slice shard
// does, scripts/vispack-slurm) find the same text and leave the file alone; a shared temporary
// name would let one remove the other's copy mid-compare. Two that both find it missing or stale
// both write the same bytes, and what depends on the file is keyed on its bytes, not its mtime
// (Fingerprint::content), so neither rewrite makes another shard's work stale.
void write_transforms_if_changed(const std::string& tpath, const StackTransforms& st) {
  bool same = false;
  try {
    same = fs::exists(tpath) && read_file(tpath) == transforms_text(st);
  } catch (const std::exception&) {
    same = false;
  }
  if (!same) write_transforms(tpath, st);
}

// The report's anchor figures (anchor mode "ct"): anchors used and down-weighted, the
// confidence-weighted residual, weak anchors, and the slices without one and why (no CT at its
// z, no body in that CT, or the alignment failed), with the warning that counts them.
void report_ct_anchors(RegisterRun& r, const StackSolve& solved, const std::vector<SlicePairs>& all,
                       nlohmann::json& warnings) {
  nlohmann::json weak = nlohmann::json::array(), unanchored = nlohmann::json::array();
  nlohmann::json outside_ct = nlohmann::json::array(), no_body = nlohmann::json::array(),
                 failed = nlohmann::json::array();
  double csum = 0, rsum2 = 0;
  int cn = 0;
  for (const auto& s : solved.slices) {
    if (s.black || s.duplicate_of) continue;
    const double conf = s.extra.value("anchor_confidence", 0.0);
    if (conf == 0.0) {
      unanchored.push_back(s.index);
      const auto& a = all[std::size_t(s.index)].anchor;
      (!a ? outside_ct : a->body_fraction < kAnchorMinBody ? no_body : failed).push_back(s.index);
    } else if (conf < 0.3) {
      weak.push_back({{"slice", s.index}, {"confidence", conf}});
    }
    if (s.extra.contains("anchor_residual_px") && conf > 0) {
      const double res = s.extra["anchor_residual_px"].get<double>();
      csum += conf, rsum2 += conf * res * res;
      ++cn;
    }
  }
  StageRun& run = r.run;
  run.set_quality("anchors_used", solved.anchors_used);
  run.set_quality("anchors_downweighted", solved.anchors_downweighted);
  run.set_quality("anchor_residual_rms_px", cn ? std::sqrt(rsum2 / csum) : 0.0);
  run.set_quality("low_confidence_anchors", weak);
  run.set_quality("unanchored_slices", unanchored);
  run.set_quality("unanchored_outside_ct", outside_ct);
  run.set_quality("unanchored_no_body", no_body);
  run.set_quality("unanchored_alignment_failed", failed);
  if (!unanchored.empty())
    warnings.push_back(cat(unanchored.size(), " slices have no CT anchor (", outside_ct.size(),
                           " outside the CT's z range, ", no_body.size(),
                           " with no body in the CT, ", failed.size(),
                           " where the alignment failed); their transforms follow their "
                           "neighbours"));
}

// The report's per-slice summary: quality (mean, min), jumps, black and duplicated slices, and
// the CT's place in the output frame.
void report_slices(RegisterRun& r, const StackTransforms& st) {
  std::vector<int> jumps, blacks;
  nlohmann::json duplicates = nlohmann::json::array();
  double qsum = 0, qmin = 1;
  int qn = 0;
  for (const auto& s : st.slices) {
    if (s.jump) jumps.push_back(s.index);
    if (s.black) blacks.push_back(s.index);
    if (s.duplicate_of) duplicates.push_back({s.index, *s.duplicate_of});
    if (!s.black && !s.duplicate_of && s.index > 0)
      qsum += s.quality, qmin = std::min(qmin, s.quality), ++qn;
  }
  StageRun& run = r.run;
  run.set_quality("mean_quality", qn ? qsum / qn : 1.0);
  run.set_quality("min_quality", qmin);
  run.set_quality("jumps", jumps);
  run.set_quality("black", blacks);
  run.set_quality("duplicates", duplicates);
  if (st.ct_to_rgb)
    run.set_quality("ct_to_rgb", {{"scale", st.ct_to_rgb->scale},
                                  {"rotation_deg", st.ct_to_rgb->rotation_deg},
                                  {"dx_px", st.ct_to_rgb->dx_px},
                                  {"dy_px", st.ct_to_rgb->dy_px},
                                  {"defined_by",
                                   "config (ct.pixel_spacing_mm, spacing_mm, "
                                   "register.output_frame)"}});
}

// transforms.json's content: the solved slices on a grid of `size`, the frame, and the CT's place
// in it (slice 0 is the reference unless the frame is the CT's).
StackTransforms stack_transforms(const StackSolve& solved, cv::Size size,
                                 const std::optional<Similarity>& ct_to_rgb) {
  StackTransforms st;
  st.width = size.width;
  st.height = size.height;
  st.center_px = {(size.width - 1) / 2.0, (size.height - 1) / 2.0};
  st.slices = solved.slices;
  st.extra["frame"] = solved.frame;
  if (solved.frame == "ct") {
    st.reference_slice.reset();
  } else {
    st.reference_slice = 0;
  }
  st.ct_to_rgb = ct_to_rgb;
  return st;
}

// Body parts each modality showed per anchored slice, and the slices to look at.
void report_anchor_parts(StageRun& run, const std::vector<std::optional<AnchorEstimate>>& anchors) {
  nlohmann::json parts = nlohmann::json::object();
  for (std::size_t k = 0; k < anchors.size(); ++k)
    if (const auto& a = anchors[k])
      parts[std::to_string(k)] = {{"ct", a->parts_ct}, {"colour", a->parts_colour}};
  run.set_quality("anchor_parts", parts);
  run.set_quality("abrupt_anchor_changes", abrupt_anchor_changes(anchors));
}

// 2. The solve, once every slice's record is present: transforms.json, the QC curves and the
// report; else the report says how many records are still missing.
void solve_records(RegisterRun& r) {
  const Config& config = r.config;
  const int n = r.n;
  const auto& files = r.files;
  StageRun& run = r.run;
  std::vector<SlicePairs> all;
  all.reserve(std::size_t(n));
  for (int k = 0; k < n; ++k) {
    auto p = load_pairs(pairs_path(config, k), r.fingerprint(k));
    if (!p) break;
    all.push_back(std::move(*p));
  }
  if (int(all.size()) != n || n == 0) {
    run.set_report("waiting",
                   cat(n - int(all.size()),
                       " slices have no pair record yet; transforms.json is written when "
                       "every shard has run"));
    return;
  }
  const cv::Size size = read_slice_size(files[0].path, config.rgb.raw);
  StackSolveOptions so;
  so.jump_px = r.reg.jump_px;
  so.overrides = r.overrides;
  so.anchor = solve_anchor_mode(r);
  StackSolve solved = solve_stack(all, size, so);
  if (so.anchor == "fiducials" && solved.fiducial_groups == 0) {
    so.anchor = "none";
    solved = solve_stack(all, size, so);
  }
  std::vector<SliceTransform>& slices = solved.slices;
  if (std::all_of(slices.begin(), slices.end(), [](const SliceTransform& t) { return t.black; }))
    throw InputError(cat(config.rgb.dir, ": all ", n, " colour slices (pattern \"",
                         config.rgb.pattern,
                         "\") are black: nothing to register or pack; check rgb.dir, "
                         "rgb.pattern and rgb.raw"));
  for (int k = 0; k < n; ++k) {
    slices[std::size_t(k)].number = files[std::size_t(k)].number;
    slices[std::size_t(k)].file = fs::path(files[std::size_t(k)].path).filename().string();
  }
  const StackTransforms st = stack_transforms(solved, size, r.ct_to_rgb);
  write_transforms_if_changed(r.tpath, st);
  // The transform curves.
  std::vector<std::optional<AnchorEstimate>> anchors(static_cast<std::size_t>(n));
  for (int k = 0; k < n; ++k)
    anchors[std::size_t(k)] = all[std::size_t(k)].anchor;
  make_directories(run.dir() + "/qc");
  write_image(run.dir() + "/qc/transforms.png",
              plot_transforms(slices, anchors, r.overrides,
                              cat(config.name, ": frame ", solved.frame, ", anchor ", so.anchor,
                                  ", ", n, " slices")));
  // Report.
  run.set_quality("anchor", so.anchor);
  report_anchor_parts(run, anchors);
  run.set_quality("frame", solved.frame);
  run.set_quality("fiducial_groups", solved.fiducial_groups);
  nlohmann::json warnings = nlohmann::json::array();
  if (so.anchor == "ct") {
    report_ct_anchors(r, solved, all, warnings);
  } else {
    warnings.push_back(
        so.anchor == "fiducials"
            ? "no CT anchor: drift is tied to the fiducial tubes only; where no tube is seen, "
              "absolute drift is not observable"
            : "no CT and no fiducials: absolute drift is not observable; the transforms are "
              "slice-to-slice estimates regularised towards no drift (window 100 slices), "
              "slice 0 is the reference");
  }
  for (const auto& w : warnings)
    warn(r.options, w.get<std::string>());
  for (const auto& w : r.z_warnings)  // printed when the stage began
    warnings.push_back(w);
  run.set_report("warnings", warnings);
  nlohmann::json over = nlohmann::json::array();
  for (const auto& o : r.overrides)
    over.push_back(to_json(o));
  run.set_report("overrides", {{"file", r.reg.overrides}, {"slices", over}});
  report_slices(r, st);
}

// Slice k's QC overlay (and, with work.write_registered, its full-size registered copy), unless
// up to date: warped from the picture written with its record when there is one, else from
// the registered colour (intermediates.h registered_colour, the one implementation the later
// stages call too).
void write_slice_outputs(RegisterRun& r, const StackTransforms& st, const StackInputs& inputs,
                         int k) {
  const Config& config = r.config;
  const auto& files = r.files;
  const auto& ct_files = r.ct_files;
  StageRun& run = r.run;
  const bool write_registered = config.work.write_registered;
  const SliceTransform& t = st.slices[std::size_t(k)];
  const CtAtZ at = ct_at_colour_slice(config, int(ct_files.size()), files[std::size_t(k)].slot);
  Fingerprint in_fp;
  in_fp.file(files[std::size_t(k)].path)
      .number(t.rigid.dx_px)
      .number(t.rigid.dy_px)
      .number(t.rigid.rotation_deg);
  if (at.inside()) in_fp.file(ct_files[std::size_t(at.below)].path);
  if (at.inside() && !at.exact())
    in_fp.number(at.w_above).file(ct_files[std::size_t(at.above)].path);
  const std::string in = in_fp.str();
  const std::string out = registered_rgb_path(config, k);
  const std::string overlay = run.slice_path("qc/overlay", k);
  std::vector<std::string> outs = {overlay};
  if (write_registered) outs.push_back(out);
  if (run.up_to_date(k, in, outs)) {
    run.skip(k);
    return;
  }
  if (!write_registered) {
    std::error_code ec;  // a copy from an earlier run must not outlive its transform
    fs::remove(out, ec);
  }
  cv::Mat hu;
  if (at.inside() && st.ct_to_rgb)
    hu = ct_hu_at_colour_slice(config, ct_files, files[std::size_t(k)].slot);
  const Similarity ct_to_rgb = st.ct_to_rgb ? *st.ct_to_rgb : Similarity{};
  const cv::Mat kept = write_registered ? cv::Mat() : recorded_picture(config, k);
  if (!kept.empty()) {
    // The overlay warped from the recorded picture: the same slice, transform and outline as
    // below, without decoding and warping the full-size slice again.
    const cv::Mat registered_small = warp_picture(kept, t.rigid, grid_size(inputs.transforms));
    write_work_image(overlay,
                     draw_ct_overlay(registered_small, hu, ct_to_rgb, config.mask.hu_threshold,
                                     kOverlayEdge, grid_size(inputs.transforms)));
    run.done(k, in, outs, 0);
    return;
  }
  const cv::Mat registered = registered_colour(config, inputs, k);
  if (write_registered) write_image(out, registered);  // the copy on request: zlib level 4
  write_work_image(
      overlay, draw_ct_overlay(registered, hu, ct_to_rgb, config.mask.hu_threshold, kOverlayEdge));
  run.done(k, in, outs, registered.total() * registered.elemSize());
}

// 3. The registered slices and QC overlays of the range, once transforms.json covers the stack.
// The registered colour is always computed for the overlay; written full size only with
// work.write_registered (inspection copies cost disk, nothing reads them back).
void write_registered_slices(RegisterRun& r) {
  std::optional<StackTransforms> st;
  try {
    if (fs::exists(r.tpath)) st = read_transforms(r.tpath);
  } catch (const std::exception&) {
    st.reset();
  }
  if (!st || int(st->slices.size()) != r.n) return;
  StackInputs inputs;
  inputs.rgb = r.files;
  inputs.ct = r.ct_files;
  inputs.transforms = *st;
  if (r.config.work.write_registered) make_directories(r.run.dir() + "/registered");
  make_directories(r.run.dir() + "/qc");
  parallel_for(r.range.size(), r.run.threads(), [&](std::int64_t i) {
    write_slice_outputs(r, *st, inputs, r.range.first + int(i));
  });
}

}  // namespace

StageResult run_register_stage(const Config& config, const StageOptions& options) {
  const std::vector<SliceFile> files = stack_slices(config);
  const int n = int(files.size());
  // CT or segmentation extents that differ from the colour stack's (slice_z.h): reported with
  // the solve's warnings.
  std::vector<std::string> z_warnings = z_extent_warnings(config, colour_slot_count(files));
  if (std::string gap = colour_gap_warning(config, files); !gap.empty())
    z_warnings.push_back(std::move(gap));
  for (const auto& w : z_warnings)
    warn(options, w);
  // A planar raw file read as interleaved (or the reverse) registers "fine" and packs a
  // scrambled volume: the middle slice's samples tell (layout_check.h; one file read).
  if (n > 0)
    check_raw_layout(config.rgb, "rgb.raw.layout", files[std::size_t(n / 2)].path, config.path);
  if (n > 0) check_raw_size(config.rgb, "rgb.raw", files[std::size_t(n / 2)].path, config.path);
  RegisterOptions reg = config.registration;
  if (!reg.enabled) reg.method = "none";
  if (reg.method != "phase+ecc" && reg.method != "phase" && reg.method != "none")
    throw ConfigError(cat(config.path, ": register.method: unknown method '", reg.method, "'"));
  const bool anchored = config.ct && reg.enabled && (reg.anchor == "auto" || reg.anchor == "ct");
  const std::vector<SliceFile> ct_files =
      config.ct ? list_slices(*config.ct) : std::vector<SliceFile>{};
  std::vector<SliceOverride> overrides;
  if (!reg.overrides.empty()) overrides = read_overrides(reg.overrides, n);
  std::vector<std::string> stage_inputs;
  if (!reg.overrides.empty()) stage_inputs.push_back(reg.overrides);
  StageRun run(config, "register", n, options,
               {"rgb", "register", "ct", "spacing_mm", "mask.hu_threshold", "mask.gel_colour",
                "mask.gel_distance", "mask.min_part_mm2", "work.write_registered"},
               stage_inputs);
  // The stage spreads slices over run.threads() workers: OpenCV's own pool stays off (with
  // --threads 1 too, so that one thread means one core, as a SLURM task of one CPU expects).
  ScopedOpenCvThreads opencv_threads(1);
  RegisterRun r(config, options, files, reg, anchored, ct_files, overrides, z_warnings, run);
  const auto t0 = std::chrono::steady_clock::now();
  if (config.ct) r.ct_to_rgb = defined_ct_to_rgb(config);
  r.anchor_options.hu_threshold = config.mask.hu_threshold;
  r.anchor_options.iterations = reg.ecc_iterations;
  if (config.ct)
    r.anchor_options.min_part_ct_px = config.mask.min_part_mm2 / (config.ct->pixel_spacing_mm[0] *
                                                                  config.ct->pixel_spacing_mm[1]);
  r.fingerprints.resize(static_cast<std::size_t>(n));

  // 1. Per-slice records of the range.
  const int pairs_computed = measure_records(r);
  const double pair_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  run.set_report("pairs_computed", pairs_computed);
  run.set_report("pair_seconds", pair_seconds);
  if (pairs_computed > 0) run.set_report("pair_seconds_per_slice", pair_seconds / pairs_computed);

  // --records-only (a cluster's measure step): stop here; the solve, the registered slices and
  // the QC overlays come from the next run over the records. Were the shard that happens to
  // finish last to solve and draw its range's overlays (~2-5 s at 2048x1216), the measure
  // step's shards would differ by that much and the step take as long as the slowest.
  if (options.records_only) {
    run.set_report("waiting",
                   cat("--records-only: ", pairs_computed, " pair records measured, ",
                       r.range.size() - pairs_computed,
                       " up to date; the solve (transforms.json), the registered slices and the "
                       "QC overlays come from the next run over the records"));
    run.add_bytes(r.bytes.load());
    return run.finish(r.tpath);
  }
  // 2. Solve when every slice's record is present.
  solve_records(r);
  // 3. Registered slices and QC overlays of the range, once transforms.json covers the stack.
  write_registered_slices(r);
  run.add_bytes(r.bytes.load());
  return run.finish(r.tpath);
}

}  // namespace vispack::pipeline

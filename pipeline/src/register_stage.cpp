// The vispack-register stage driver: pair records (sharded), chaining, CT alignment, registered
// slices. See register.h for how shards combine.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/common/progress.h"
#include "vispack/pipeline/mask.h"
#include "vispack/pipeline/register.h"
#include "vispack/pipeline/slice_io.h"

namespace vispack::pipeline {
namespace {

namespace fs = std::filesystem;

constexpr double kOutlineDistance = 80.0;  // colour distance from the gel of the RGB outline

std::string pairs_path(const Config& config, int k) {
  return slice_output_path(config, "register", "pairs/pairs", k, "json");
}

// Fingerprint of what the pair record of slice k depends on: the register config section and
// the files k−4..k.
std::string pair_fingerprint(const Config& config, const std::vector<SliceFile>& files, int k) {
  Fingerprint fp;
  fp.text("pairs-v2");  // the record's layout and method version (v2: fiducials)
  fp.text(config_section_hash(config, {"register"}));
  for (int j = std::max(0, k - 4); j <= k; ++j)
    fp.file(files[std::size_t(j)].path);
  return fp.str();
}

// The stored pair record of slice k if it exists and is current.
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

cv::Mat to_rgb8(const cv::Mat& m) {
  cv::Mat out = m;
  if (m.depth() == CV_16U) m.convertTo(out, CV_8U, 255.0 / 65535.0);
  if (out.channels() == 1) cv::cvtColor(out, out, cv::COLOR_GRAY2RGB);
  return out;
}

cv::Mat read_ct_hu(const CtSource& ct, const std::string& path) {
  cv::Mat raw = read_slice(path, ct.raw);
  if (raw.channels() != 1) throw InputError(cat(path, ": CT slice must be single-channel"));
  cv::Mat hu;
  raw.convertTo(hu, CV_32F, ct.slope, ct.intercept);
  return hu;
}

// ct_to_rgb from up to 5 usable slices around the middle of the stack (median of each
// parameter over the slices where the refinement succeeded).
std::optional<CtToRgb> align_ct(const Config& config, const std::vector<SliceFile>& files,
                                const std::vector<SliceTransform>& t, nlohmann::json& report) {
  if (!config.ct) return std::nullopt;
  const RigidGuess& g = config.registration.ct_initial;
  Similarity initial{g.scale, g.rotation_deg, g.dx_px, g.dy_px};
  CtToRgb result{initial.scale, initial.rotation_deg, initial.dx_px, initial.dy_px};
  report["ct_initial"] = {initial.scale, initial.rotation_deg, initial.dx_px, initial.dy_px};
  if (!config.registration.ct_refine) return result;
  const std::vector<SliceFile> ct_files = list_slices(*config.ct);
  const int n = int(files.size());
  std::vector<int> picks;
  for (int i = 1; i <= 5; ++i) {
    int k = int(std::lround(n * (0.25 + 0.5 * (i - 1) / 4.0)));
    k = std::clamp(k, 0, n - 1);
    const int ct_k = k + config.ct->slice_offset;
    if (t[k].black || t[k].duplicate_of || ct_k < 0 || ct_k >= int(ct_files.size())) continue;
    if (std::find(picks.begin(), picks.end(), k) == picks.end()) picks.push_back(k);
  }
  std::vector<Similarity> found(picks.size());
  std::vector<char> ok(picks.size(), 0);
  parallel_for(std::int64_t(picks.size()), 0, [&](std::int64_t i) {
    const int k = picks[std::size_t(i)];
    cv::Mat observed = to_rgb8(read_slice(files[k].path, config.rgb.raw));
    cv::Mat registered;
    cv::warpAffine(
        observed, registered,
        cv::Mat(output_to_observed(t[k], {(observed.cols - 1) / 2.0, (observed.rows - 1) / 2.0})),
        observed.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
    const cv::Vec3f gel = config.mask.gel_colour ? cv::Vec3f(float((*config.mask.gel_colour)[0]),
                                                             float((*config.mask.gel_colour)[1]),
                                                             float((*config.mask.gel_colour)[2]))
                                                 : estimate_gel_colour(registered);
    // The outline for the alignment sits nearer the middle of the gel→tissue edge than the
    // mask's gel_distance: tissue showing through the translucent gel next to the body lies
    // 40..50 from the gel colour and would move a 40-threshold outline outwards (by ~1 % in
    // scale on the phantom).
    cv::Mat rgb_outline =
        colour_body_mask(registered, gel, std::max(kOutlineDistance, config.mask.gel_distance), 2);
    cv::Mat ct_outline = ct_body_mask(
        read_ct_hu(*config.ct, ct_files[std::size_t(k + config.ct->slice_offset)].path),
        config.mask.hu_threshold);
    bool good = false;
    found[std::size_t(i)] = align_ct_to_rgb(ct_outline, rgb_outline, initial, &good);
    ok[std::size_t(i)] = good;
  });
  std::vector<double> s, r, x, y;
  nlohmann::json per = nlohmann::json::array();
  for (std::size_t i = 0; i < picks.size(); ++i) {
    per.push_back({{"slice", picks[i]},
                   {"ok", bool(ok[i])},
                   {"scale", found[i].scale},
                   {"rotation_deg", found[i].rotation_deg},
                   {"dx_px", found[i].dx_px},
                   {"dy_px", found[i].dy_px}});
    if (!ok[i]) continue;
    s.push_back(found[i].scale), r.push_back(found[i].rotation_deg);
    x.push_back(found[i].dx_px), y.push_back(found[i].dy_px);
  }
  report["ct_alignment_slices"] = per;
  if (s.empty()) {
    report["ct_alignment"] = "initial guess kept (refinement failed)";
    return result;
  }
  auto median = [](std::vector<double> v) {
    std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
    return v[v.size() / 2];
  };
  report["ct_alignment"] = "refined";
  return CtToRgb{median(s), median(r), median(x), median(y)};
}

}  // namespace

StageResult run_register_stage(const Config& config, const StageOptions& options) {
  const std::vector<SliceFile> files = stack_slices(config);
  const int n = int(files.size());
  RegisterOptions reg = config.registration;
  if (!reg.enabled) reg.method = "none";
  if (reg.method != "phase+ecc" && reg.method != "phase" && reg.method != "none")
    throw ConfigError(cat(config.path, ": register.method: unknown method '", reg.method, "'"));
  StageRun run(
      config, "register", n, options,
      {"rgb", "register", "ct", "mask.hu_threshold", "mask.gel_colour", "mask.gel_distance"});
  ScopedOpenCvThreads opencv_threads(run.threads() > 1 ? 1 : cv::getNumThreads());
  const SliceRange range = run.range();
  const auto t0 = std::chrono::steady_clock::now();

  // 1. Pair records of the range.
  make_directories(run.dir() + "/pairs");
  std::vector<std::string> fingerprints(static_cast<std::size_t>(n));
  int first_missing = range.last, last_missing = range.first - 1;
  for (int k = range.first; k < range.last; ++k) {
    fingerprints[std::size_t(k)] = pair_fingerprint(config, files, k);
    if (options.force || !load_pairs(pairs_path(config, k), fingerprints[std::size_t(k)])) {
      first_missing = std::min(first_missing, k);
      last_missing = std::max(last_missing, k);
    }
  }
  cv::Size size;
  std::atomic<std::uint64_t> bytes{0};
  int pairs_computed = 0;
  if (first_missing <= last_missing) {
    // Every slice must have the first slice's size (issue 7: a slice replaced between runs).
    const cv::Size stack_size = read_slice(files[0].path, config.rgb.raw).size();
    auto frame = [&](int k) {
      cv::Mat slice = read_slice(files[std::size_t(k)].path, config.rgb.raw);
      if (slice.size() != stack_size)
        throw InputError(cat(files[std::size_t(k)].path, ": slice is ", slice.cols, "x", slice.rows,
                             ", the stack (", files[0].path, ") is ", stack_size.width, "x",
                             stack_size.height));
      bytes += slice.total() * slice.elemSize();
      return prepare_frame(slice, reg);
    };
    std::vector<SlicePairs> computed =
        compute_pairs(first_missing, last_missing + 1, frame, reg, run.threads());
    for (const auto& p : computed) {
      nlohmann::json j = to_json(p);
      j["fingerprint"] = fingerprints[std::size_t(p.index)];
      write_file_atomic(pairs_path(config, p.index), j.dump(1) + "\n");
    }
    pairs_computed = int(computed.size());
  }
  const double pair_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  run.set_report("pairs_computed", pairs_computed);
  run.set_report("pair_seconds", pair_seconds);
  if (pairs_computed > 0) run.set_report("pair_seconds_per_slice", pair_seconds / pairs_computed);

  // 2. Chain when every slice's record is present.
  std::vector<SlicePairs> all;
  all.reserve(std::size_t(n));
  for (int k = 0; k < n; ++k) {
    const std::string fp = fingerprints[std::size_t(k)].empty() ? pair_fingerprint(config, files, k)
                                                                : fingerprints[std::size_t(k)];
    auto p = load_pairs(pairs_path(config, k), fp);
    if (!p) break;
    all.push_back(std::move(*p));
  }
  const std::string tpath = transforms_path(config);
  if (int(all.size()) == n && n > 0) {
    cv::Mat first = read_slice(files[0].path, config.rgb.raw);
    size = first.size();
    int fiducial_groups = 0;
    std::vector<SliceTransform> chained =
        chain_transforms(all, size, reg.jump_px, &fiducial_groups);
    run.set_quality("fiducial_groups", fiducial_groups);
    for (int k = 0; k < n; ++k) {
      chained[std::size_t(k)].number = files[std::size_t(k)].number;
      chained[std::size_t(k)].file = fs::path(files[std::size_t(k)].path).filename().string();
    }
    StackTransforms st;
    st.width = size.width;
    st.height = size.height;
    st.center_px = {(size.width - 1) / 2.0, (size.height - 1) / 2.0};
    st.slices = chained;
    nlohmann::json ct_report = nlohmann::json::object();
    st.ct_to_rgb = align_ct(config, files, chained, ct_report);
    run.set_report("ct", ct_report);
    // Rewrite only on change, so later stages (whose staleness follows this file) stay current.
    bool same = false;
    try {
      if (fs::exists(tpath)) {
        const std::string tmp = tpath + ".compare";
        write_transforms(tmp, st);
        same = read_file(tmp) == read_file(tpath);
        fs::remove(tmp);
      }
    } catch (const std::exception&) {
      same = false;
    }
    if (!same) write_transforms(tpath, st);
    // Quality summary.
    std::vector<int> jumps, blacks;
    nlohmann::json duplicates = nlohmann::json::array();
    double qsum = 0, qmin = 1;
    int qn = 0;
    for (const auto& s : chained) {
      if (s.jump) jumps.push_back(s.index);
      if (s.black) blacks.push_back(s.index);
      if (s.duplicate_of) duplicates.push_back({s.index, *s.duplicate_of});
      if (!s.black && !s.duplicate_of && s.index > 0)
        qsum += s.quality, qmin = std::min(qmin, s.quality), ++qn;
    }
    run.set_quality("mean_quality", qn ? qsum / qn : 1.0);
    run.set_quality("min_quality", qmin);
    run.set_quality("jumps", jumps);
    run.set_quality("black", blacks);
    run.set_quality("duplicates", duplicates);
    if (st.ct_to_rgb)
      run.set_quality("ct_to_rgb", {{"scale", st.ct_to_rgb->scale},
                                    {"rotation_deg", st.ct_to_rgb->rotation_deg},
                                    {"dx_px", st.ct_to_rgb->dx_px},
                                    {"dy_px", st.ct_to_rgb->dy_px}});
  } else {
    run.set_report("waiting",
                   cat(n - int(all.size()),
                       " slices have no pair record yet; transforms.json is written when "
                       "every shard has run"));
  }

  // 3. Registered slices of the range, once transforms.json covers the whole stack.
  std::optional<StackTransforms> st;
  try {
    if (fs::exists(tpath)) st = read_transforms(tpath);
  } catch (const std::exception&) {
    st.reset();
  }
  if (st && int(st->slices.size()) == n) {
    make_directories(run.dir() + "/registered");
    parallel_for(range.size(), run.threads(), [&](std::int64_t i) {
      const int k = range.first + int(i);
      const SliceTransform& t = st->slices[std::size_t(k)];
      const std::string in = Fingerprint()
                                 .file(files[std::size_t(k)].path)
                                 .number(t.dx_px)
                                 .number(t.dy_px)
                                 .number(t.rotation_deg)
                                 .str();
      const std::string out = registered_rgb_path(config, k);
      if (run.up_to_date(k, in, {out})) {
        run.skip(k);
        return;
      }
      cv::Mat observed = to_rgb8(read_slice(files[std::size_t(k)].path, config.rgb.raw));
      if (observed.cols != st->width || observed.rows != st->height)
        throw InputError(cat(files[std::size_t(k)].path, ": slice is ", observed.cols, "x",
                             observed.rows, ", the stack is ", st->width, "x", st->height));
      cv::Mat registered;
      cv::warpAffine(observed, registered, cv::Mat(output_to_observed(t, st->center_px)),
                     observed.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                     cv::BORDER_REPLICATE);
      write_image(out, registered);
      run.done(k, in, {out}, observed.total() * observed.elemSize());
    });
  }
  run.add_bytes(bytes.load());
  return run.finish(tpath);
}

}  // namespace vispack::pipeline

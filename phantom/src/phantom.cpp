#include "vispack/phantom/phantom.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <mutex>
#include <regex>
#include <utility>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "phantom_folder.h"
#include "phantom_model.h"
#include "truth_json.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/common/nrrd.h"
#include "vispack/common/parallel.h"
#include "vispack/common/progress.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vispack::phantom {
namespace {

namespace fs = std::filesystem;
using namespace detail;
using pipeline::RawLayout;
using pipeline::write_image;
using pipeline::write_raw_slice;
using ojson = nlohmann::ordered_json;

constexpr double kNoiseSigma = 3.0;              // RGB sensor noise, 8-bit levels
constexpr double kCtNoiseHu = 6.0;               // CT noise, HU
constexpr double kGainRange = 0.05;              // brightness gain 1 ± 5 %
constexpr double kDriftPx = 0.3;                 // random-walk step σ, pixels
constexpr double kDriftDeg = 0.05;               // random-walk step σ, degrees
constexpr double kSystematicDegPerSlice = 0.02;  // DriftModel::kRotation
constexpr double kBlockGainRange = 0.08;         // --blocks: brightness step per block, 1 ± 8 %

struct SliceTruth {
  double dx = 0, dy = 0, rot = 0, gain = 1;
  bool jump = false, black = false;
  int duplicate_of = -1;
  int source = 0;  // model slice whose picture the observed file shows (k, or k−1 for a duplicate)
};

struct Plan {
  PhantomPreset preset;
  int slices = 0;
  bool defects = false;
  int jump = -1, black = -1, duplicate = -1;  // the first jump, the first black slice
  std::vector<int> jumps, blacks;             // every block jump, every black slice
  std::vector<int> block_starts;              // --blocks: the first slice of each block
  std::vector<double> block_gains;            // --blocks: each block's brightness factor
  std::vector<SliceTruth> truth;
  Anatomy anatomy;
  // CT → output grid: the output grid IS the CT frame at the colour resolution
  // (docs/ARCHITECTURE.md "The output frame"), so ct_to_rgb is the pixel-size ratio turned and
  // shifted by output_frame (identity).
  double ct_scale = 1, ct_rot = 0, ct_dx = 0, ct_dy = 0;
  pipeline::Rigid output_frame;                // register.output_frame of the config written
  double cam_rot = 0, cam_dx = 0, cam_dy = 0;  // the colour camera's constant offset
  int digits = 4;
};

// Shift limits that keep the body inside the frame under any recorded rotation.
struct Limits {
  double x, y, rot;
};
Limits limits_for(const PhantomPreset& p, const Anatomy& anatomy, double max_rot_deg) {
  const double half = p.height * 0.5;
  const double a = Model::body_max_a(anatomy), b = Model::body_max_b(anatomy);
  const double reach = std::hypot(a, b) * half;  // farthest body point from the centre, px
  const double rot_px = max_rot_deg * kPi / 180.0 * reach;
  return {p.width * 0.5 - a * half - 3 - rot_px, half - b * half - 2 - rot_px, max_rot_deg};
}

double reflect(double v, double limit) {
  for (int i = 0; i < 4 && std::fabs(v) > limit; ++i)
    v = v > 0 ? 2 * limit - v : -2 * limit - v;
  return std::clamp(v, -limit, limit);
}

// The preset with the options applied (CT scale), the options checked, and the anatomy.
void plan_preset(const PhantomOptions& options, Plan& plan) {
  plan.preset = phantom_preset(options.preset);
  if (options.ct_scale < 0 || (options.ct_scale > 0 && options.ct_scale < 0.25) ||
      options.ct_scale > 16)
    throw UsageError(cat("--ct-scale ", options.ct_scale, ": must be between 0.25 and 16"));
  for (const auto& [name, every] : {std::pair<const char*, int>{"--ct-every", options.ct_every},
                                    {"--seg-every", options.seg_every}})
    if (every < 1 || every > 1000) throw UsageError(cat(name, " ", every, ": must be 1..1000"));
  if (options.ct_scale > 0) {
    // CT pixels ct_scale× the colour pixel, a field of view 10 % larger than the colour frame.
    PhantomPreset& q = plan.preset;
    q.ct_pixel_mm = q.pixel_mm * options.ct_scale;
    q.ct_size = int(std::ceil(1.1 * std::max(q.width, q.height) * q.pixel_mm / q.ct_pixel_mm));
  }
  const PhantomPreset& p = plan.preset;
  plan.anatomy.fiducials = options.fiducials.value_or(p.fiducials);
  if (p.varying_anatomy) {
    plan.anatomy.varying = true;
    plan.anatomy.body_scale = 0.8;
    plan.anatomy.shift_x = 0.3;
    plan.anatomy.shift_y = 0.12;
    plan.anatomy.taper = true;
    if (p.limbs) {
      // A whole body (phantom_model.h Anatomy::limbs): its own outline along z, centred; the
      // table 2.5 CT pixels thick (the opening of the CT mask detaches it).
      plan.anatomy.body_scale = 1.0;
      plan.anatomy.shift_x = plan.anatomy.shift_y = 0.0;
      plan.anatomy.taper = false;
      plan.anatomy.limbs = true;
      plan.anatomy.table_px = 2.5 * p.ct_pixel_mm / p.pixel_mm;
    }
  }
}

// The block jumps: one at N/2, or with --blocks B one at each of the B − 1 boundaries of B blocks
// of equal length, each block with its own brightness factor (drawn from a generator of its own,
// so the walk and the per-slice gains stay those of a folder without blocks).
void plan_blocks(const PhantomOptions& options, Plan& plan) {
  const int n = plan.slices, b = options.blocks;
  if (b == 0 || b == 1) {
    if (options.jump) plan.jumps.push_back(n / 2);
    return;
  }
  if (b < 0 || b > 64 || n < 4 * b)
    throw UsageError(
        cat("--blocks ", b, ": must be 2..64 and at most slices / 4 (", n, " slices)"));
  Random gains(options.seed * 0xa0761d6478bd642full + 41);
  for (int i = 0; i < b; ++i) {
    plan.block_starts.push_back(int((std::int64_t(i) * n) / b));
    plan.block_gains.push_back(1.0 + gains.uniform(-kBlockGainRange, kBlockGainRange));
    if (i > 0 && options.jump) plan.jumps.push_back(plan.block_starts.back());
  }
}

// --black-slices C: C black slices at the middles of C equal parts of the stack, each moved on
// past slice 0, a jump, the duplicate and its source, and the black slices already placed.
template <class IsJump>
void plan_black_slices(const PhantomOptions& options, Plan& plan, const IsJump& is_jump) {
  const int n = plan.slices, c = options.black_slices;
  if (c < 0 || c > n / 4)
    throw UsageError(cat("--black-slices ", c, ": must be 0..slices / 4 (", n, " slices)"));
  for (int i = 0; i < c; ++i) {
    int k = int(((2 * std::int64_t(i) + 1) * n) / (2 * std::int64_t(c)));
    auto taken = [&](int j) {
      return j == 0 || is_jump(j) || j == plan.duplicate || j + 1 == plan.duplicate ||
             std::find(plan.blacks.begin(), plan.blacks.end(), j) != plan.blacks.end();
    };
    int tries = 0;
    while (taken(k) && tries++ < n)
      k = (k + 1) % n;
    if (taken(k)) throw UsageError(cat("--black-slices ", c, ": no room in ", n, " slices"));
    plan.blacks.push_back(k);
  }
  std::sort(plan.blacks.begin(), plan.blacks.end());
  if (!plan.blacks.empty()) plan.black = plan.blacks.front();
}

// The slice count (checked, with the truth volumes' memory), the file digits and where the
// jumps and the defects go.
void plan_slices(const PhantomOptions& options, Plan& plan) {
  const PhantomPreset& p = plan.preset;
  plan.slices = options.slices > 0 ? options.slices : p.slices;
  if (options.slices < 0 || plan.slices < 2 || plan.slices > 100000) {
    throw UsageError(cat("--slices ", options.slices, ": must be between 2 and 100000"));
  }
  const int n = plan.slices;
  // The preset's default quietly drops the defects for very short stacks; asking for them fails.
  plan.defects = options.defects.value_or(p.defects && n >= 6);
  if (plan.defects && n < 6) {
    throw UsageError(cat("black/duplicate slices (--defects) need at least 6 slices, got ", n));
  }
  // Bytes per voxel of the truth volumes: rgb 3 + ct 2 + mask 1 + labels 2 + seg_labels 2.
  const double volume_bytes = double(p.width) * p.height * n * 10.0;
  if (options.truth_every < 0 || options.truth_every > 100000)
    throw UsageError(cat("--truth-every ", options.truth_every, ": must be 0..100000"));
  if (options.truth_every < 2 && volume_bytes > 12e9) {
    throw UsageError(cat("--slices ", n, ": the truth volumes would need ",
                         std::llround(volume_bytes / 1e9),
                         " GB of memory; use fewer slices or --truth-every K (a streamed folder)"));
  }
  plan.digits = std::max(4, int(std::to_string(n - 1).size()));
  plan_blocks(options, plan);
  plan.jump = plan.jumps.empty() ? -1 : plan.jumps.front();
  auto is_jump = [&](int k) {
    return std::find(plan.jumps.begin(), plan.jumps.end(), k) != plan.jumps.end();
  };
  if (plan.defects) {
    plan.black = std::max(1, n / 4);
    plan.duplicate = (3 * n) / 4;
    while (is_jump(plan.duplicate))
      ++plan.duplicate;
    if (plan.duplicate - 1 == plan.black) ++plan.duplicate;
    if (plan.duplicate >= n) throw UsageError("too few slices for the defects");
    plan.blacks.push_back(plan.black);
  }
  plan_black_slices(options, plan, is_jump);
}

// The drift models other than the walk (PhantomOptions::DriftModel) change the walk's steps. They
// draw from their own generator, so the gains and the jump are the same whatever the model (and
// the walk's folder is byte-identical to one made before the models existed).
class DriftSteps {
 public:
  DriftSteps(const PhantomOptions& options, int height, int slices)
      : model_(options.drift_model),
        heavy_rng_(options.seed * 0x2545f4914f6cdd1dull + 31),
        bow_px_(std::max(1.0, 0.02 * height)),
        slices_(slices) {}

  // Slice k's steps (px, px, degrees) as the walk drew them, changed by the model.
  void apply(int k, double drift, double& step_x, double& step_y, double& step_r) {
    using Model = PhantomOptions::DriftModel;
    if (model_ == Model::kHeavy) {
      step_x = drift * t2(kDriftPx), step_y = drift * t2(kDriftPx), step_r = drift * t2(kDriftDeg);
    } else if (model_ == Model::kRotation) {
      step_r += drift * kSystematicDegPerSlice;
    } else if (model_ == Model::kBowed && k > 0) {
      step_x += drift * (bow(k) - bow(k - 1));
      step_y += drift * (bow(k) - bow(k - 1));
    }
  }

 private:
  // Student's t with 2 degrees of freedom, capped at 15 σ: a normal over sqrt(chi²₂ / 2) =
  // sqrt(−ln U).
  double t2(double sigma) {
    const double u = std::max(heavy_rng_.uniform(), 1e-300);
    return std::clamp(heavy_rng_.normal(1.0) / std::sqrt(-std::log(u)), -15.0, 15.0) * sigma;
  }
  double bow(int k) const { return bow_px_ * std::sin(kPi * k / std::max(1, slices_ - 1)); }

  PhantomOptions::DriftModel model_;
  Random heavy_rng_;
  double bow_px_;
  int slices_;
};

// The block jump's magnitude range, px: --jump-px, else 7..9 on frames under 128 px high, 10..15.
std::pair<double, double> jump_range(const PhantomOptions& options, bool tiny) {
  if (options.jump_px_min <= 0 && options.jump_px_max <= 0)
    return tiny ? std::pair{7.0, 9.0} : std::pair{10.0, 15.0};
  if (!(options.jump_px_min > 0 && options.jump_px_min <= options.jump_px_max &&
        options.jump_px_max <= 100)) {
    throw UsageError(cat("--jump-px ", options.jump_px_min, ":", options.jump_px_max,
                         ": needs 0 < MIN <= MAX <= 100 px"));
  }
  return {options.jump_px_min, options.jump_px_max};
}

// The colour camera's constant offset against the CT: about 0.05·H px (3..12) and 1..2°
// (tiny: 0.6..1.2°), never more than 40 % of the room the drift has.
void plan_camera_offset(const PhantomOptions& options, const Limits& lim, bool tiny, Plan& plan) {
  const PhantomPreset& p = plan.preset;
  Random cam(options.seed * 0xd1b54a32d192ed03ull + 29);
  const double mag = std::min(std::clamp(0.05 * p.height, 3.0, 12.0), 0.4 * std::min(lim.x, lim.y));
  const double angle = cam.uniform(0, 2 * kPi);
  plan.cam_rot = cam.uniform(1.0, 2.0) * (tiny ? 0.6 : 1.0) * (cam.uniform() < 0.5 ? -1 : 1);
  plan.cam_dx = mag * std::cos(angle);
  plan.cam_dy = mag * std::sin(angle);
}

// Each slice's true transform: the camera offset, a random walk reflected at the limits, one
// block jump (turned until it fits), the black and the duplicated slice.
void plan_drift(const PhantomOptions& options, const Limits& lim, bool tiny, Plan& plan) {
  const PhantomPreset& p = plan.preset;
  const int n = plan.slices;
  const auto [jump_lo, jump_hi] = jump_range(options, tiny);
  const double rot_lo = tiny ? 1.5 : 2.0, rot_hi = tiny ? 2.5 : 4.0;
  Random rng(options.seed * 0x9e3779b97f4a7c15ull + 17);
  DriftSteps model_steps(options, p.height, n);
  plan.truth.resize(n);
  auto listed = [](const std::vector<int>& v, int k) {
    return std::find(v.begin(), v.end(), k) != v.end();
  };
  std::size_t block = 0;
  for (int k = 0; k < n; ++k) {
    SliceTruth& s = plan.truth[k];
    s.source = k;
    s.gain = 1.0 + rng.uniform(-kGainRange, kGainRange);
    while (block + 1 < plan.block_starts.size() && plan.block_starts[block + 1] <= k)
      ++block;
    if (!plan.block_gains.empty()) s.gain *= plan.block_gains[block];
    const double drift = options.drift ? 1.0 : 0.0;  // the draws happen either way
    double step_x = drift * rng.normal(kDriftPx), step_y = drift * rng.normal(kDriftPx);
    double step_r = drift * rng.normal(kDriftDeg);
    model_steps.apply(k, drift, step_x, step_y, step_r);
    const double jump_m = rng.uniform(jump_lo, jump_hi), jump_a = rng.uniform(0, 2 * kPi);
    const double jump_r = rng.uniform(rot_lo, rot_hi) * (rng.uniform() < 0.5 ? -1 : 1);
    if (k == 0) {
      s.dx = plan.cam_dx, s.dy = plan.cam_dy, s.rot = plan.cam_rot;  // no reference slice
      continue;
    }
    const SliceTruth& prev = plan.truth[k - 1];
    if (k == plan.duplicate) {
      // An exact copy of the previous file: same picture, same transform.
      s = prev;
      s.jump = false;
      s.black = false;
      s.duplicate_of = k - 1;
      s.source = prev.source;
      continue;
    }
    s.dx = reflect(prev.dx + step_x, lim.x);
    s.dy = reflect(prev.dy + step_y, lim.y);
    s.rot = reflect(prev.rot + step_r, lim.rot);
    if (listed(plan.jumps, k)) {
      // Try directions around the drawn one until the whole jump fits inside the limits.
      bool placed = false;
      for (int attempt = 0; attempt < 8 && !placed; ++attempt) {
        const double a = jump_a + attempt * kPi / 4;
        const double jx = prev.dx + jump_m * std::cos(a), jy = prev.dy + jump_m * std::sin(a);
        if (std::fabs(jx) <= lim.x && std::fabs(jy) <= lim.y) {
          s.dx = jx;
          s.dy = jy;
          placed = true;
        }
      }
      if (!placed) {
        throw Error(cat("phantom: no room for a block jump of ", jump_m, " px in a ", p.width, "x",
                        p.height, " frame"));
      }
      s.rot = std::clamp(prev.rot + jump_r, -lim.rot, lim.rot);
      if (std::fabs(s.rot - prev.rot) < rot_lo * 0.99) s.rot = prev.rot - jump_r;
      s.jump = true;
    }
    s.black = listed(plan.blacks, k);
  }
}

Plan make_plan(const PhantomOptions& options) {
  Plan plan;
  plan_preset(options, plan);
  plan_slices(options, plan);
  const PhantomPreset& p = plan.preset;
  const bool tiny = p.height < 128;
  const Limits lim = limits_for(p, plan.anatomy, tiny ? 3.5 : 6.0);
  plan_camera_offset(options, lim, tiny, plan);
  plan_drift(options, lim, tiny, plan);
  // CT → output grid: defined, not drawn (output_frame identity by default).
  plan.ct_scale = p.ct_pixel_mm / p.pixel_mm;
  plan.ct_rot = plan.output_frame.rotation_deg;
  plan.ct_dx = plan.output_frame.dx_px;
  plan.ct_dy = plan.output_frame.dy_px;
  return plan;
}

// Removes files of an earlier run (same naming scheme) that this run did not write.
void remove_stale(const std::string& dir, const std::regex& pattern,
                  const std::vector<std::string>& keep) {
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (!std::regex_match(name, pattern)) continue;
    if (std::find(keep.begin(), keep.end(), name) != keep.end()) continue;
    fs::remove(it->path(), ec);
  }
}

}  // namespace

PhantomPreset phantom_preset(const std::string& name) {
  PhantomPreset p;
  p.name = name;
  if (name == "tiny") {
    p.width = 96, p.height = 64, p.slices = 24, p.pixel_mm = 0.5, p.ct_size = 56,
    p.ct_pixel_mm = 1.0, p.defects = false;
  } else if (name == "small") {
    p.width = 256, p.height = 192, p.slices = 64, p.pixel_mm = 0.33, p.ct_size = 128,
    p.ct_pixel_mm = 0.9, p.defects = true;
  } else if (name == "medium") {
    p.width = 512, p.height = 384, p.slices = 160, p.pixel_mm = 0.33, p.ct_size = 256,
    p.ct_pixel_mm = 0.9, p.defects = true;
  } else if (name == "vhp") {
    p.width = 2048, p.height = 1216, p.slices = 16, p.pixel_mm = 0.33, p.ct_size = 512,
    p.ct_pixel_mm = 1.4, p.defects = true;
  } else if (name == "anatomy") {
    // Does not flatter registration: anatomy that moves, grows and vanishes along z, tapering to
    // nothing at both ends; no fiducials; fresh texture every slice; CT 2× coarser.
    p.width = 256, p.height = 192, p.slices = 96, p.pixel_mm = 0.33, p.ct_size = 144,
    p.ct_pixel_mm = 0.66, p.defects = false, p.fiducials = false, p.varying_anatomy = true;
  } else if (name == "anatomy-vhp") {
    p.width = 2048, p.height = 1216, p.slices = 16, p.pixel_mm = 0.33, p.ct_size = 1120,
    p.ct_pixel_mm = 0.66, p.defects = false, p.fiducials = false, p.varying_anatomy = true;
  } else if (name == "male") {
    // A whole body with arms, legs and toes at the real slice size (docs/ARCHITECTURE.md, 'The body
    // mask: every part is body').
    p.width = 2048, p.height = 1216, p.slices = 200, p.pixel_mm = 0.33, p.ct_size = 512,
    p.ct_pixel_mm = 1.4, p.defects = false, p.fiducials = false, p.varying_anatomy = true,
    p.limbs = true;
  } else if (name == "korean") {
    // The male body on a Visible Korean colour slice (4368×2912, 0.1 mm), CT 1 mm.
    p.width = 4368, p.height = 2912, p.slices = 64, p.pixel_mm = 0.1, p.ct_size = 481,
    p.ct_pixel_mm = 1.0, p.defects = false, p.fiducials = false, p.varying_anatomy = true,
    p.limbs = true;
  } else if (name == "male-small") {
    p.width = 384, p.height = 228, p.slices = 64, p.pixel_mm = 0.33, p.ct_size = 282,
    p.ct_pixel_mm = 0.495, p.defects = false, p.fiducials = false, p.varying_anatomy = true,
    p.limbs = true;
  } else {
    throw UsageError(cat("unknown preset \"", name,
                         "\" (use tiny, small, medium, vhp, anatomy, anatomy-vhp, male, korean "
                         "or male-small)"));
  }
  p.slice_mm = 1.0;
  return p;
}

PhantomOptions::DriftModel parse_drift_model(const std::string& name) {
  using Model = PhantomOptions::DriftModel;
  if (name == "walk") return Model::kWalk;
  if (name == "heavy") return Model::kHeavy;
  if (name == "rotation") return Model::kRotation;
  if (name == "bowed") return Model::kBowed;
  throw UsageError(cat("--drift '", name, "': not walk, heavy, rotation or bowed"));
}

namespace {

// What rendering and writing one preset phantom needs: the plan, the options, the model and the
// folder being written. Slices may be rendered from many threads at once (each writes its own
// planes and files).
struct PresetRun {
  const Plan& plan;
  const PhantomOptions& options;
  const Model& model;
  const GaussianTable& gaussian;
  PhantomFolder& folder;
  std::string rgb_ext, seg_ext;
  RawLayout raw;
  std::vector<int> truth_sample;  // a streamed folder's truth slices (truth_every ≥ 2)
};

// Slice k of the truth volumes on the output grid: no drift, no noise, gain 1.
void render_truth(const PresetRun& r, const TruthPlanes& truth, const SliceParams& params) {
  const int W = r.plan.preset.width, H = r.plan.preset.height;
  Sample sample;
  for (int y = 0; y < H; ++y) {
    for (int x = 0; x < W; ++x) {
      r.model.eval(params, x, y, 1.0, true, true, sample);
      truth.set(std::size_t(y) * W + x, sample.rgb, sample.hu, -1024L, 3071L, sample.body,
                sample.label);
    }
  }
}

// Observed RGB and segmentation of slice k, written: the model sampled at q(p) for each observed
// pixel p, q = c + R(−θ)(p − c − d) (the inverse of p = c + R(θ)(q − c) + d). The IDs the seg
// slice shows go to truth/seg_labels, pixel for pixel on its own (drifted) grid; 0 on a black
// slice. A streamed folder keeps no seg_labels (`t_seg` null).
void render_observed(const PresetRun& r, int k, const SliceParams& params, std::uint16_t* t_seg) {
  const SliceTruth& st = r.plan.truth[k];
  const int W = r.plan.preset.width, H = r.plan.preset.height;
  const double cx = (W - 1) * 0.5, cy = (H - 1) * 0.5;
  cv::Mat rgb(H, W, CV_8UC3, cv::Scalar::all(0));
  cv::Mat seg(H, W, CV_8UC3, cv::Scalar::all(0));
  if (!st.black) {
    Sample sample;
    const SliceParams& src = st.source == k ? params : r.model.slice(st.source);
    const double th = st.rot * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
    Random noise(mix64(r.options.seed ^ (0x5851f42d4c957f2dull * std::uint64_t(st.source + 1))));
    for (int y = 0; y < H; ++y) {
      auto* row = rgb.ptr<std::uint8_t>(y);
      auto* srow = seg.ptr<std::uint8_t>(y);
      for (int x = 0; x < W; ++x) {
        const double px = x - cx - st.dx, py = y - cy - st.dy;
        const double qx = cx + cs * px + sn * py, qy = cy - sn * px + cs * py;
        r.model.eval(src, qx, qy, 1.0, true, false, sample);
        float gauss[4];
        noise.normal4(r.gaussian, gauss);
        for (int c = 0; c < 3; ++c) {
          row[x * 3 + c] = to_u8(sample.rgb[c] * st.gain + kNoiseSigma * gauss[c]);
        }
        if (t_seg) t_seg[std::size_t(y) * W + x] = sample.label;
        const auto& colour = label_info(sample.label).palette;
        for (int c = 0; c < 3; ++c)
          srow[x * 3 + c] = static_cast<std::uint8_t>(colour[c]);
      }
    }
  }
  if (r.options.rgb_raw) {
    write_raw_slice(r.folder.dir() + "/rgb/" + r.folder.rgb_name(k, r.rgb_ext), rgb, r.raw);
  } else {
    r.folder.write_rgb(k, r.rgb_ext, rgb);
  }
  if (k % r.options.seg_every == 0) r.folder.write_seg(k / r.options.seg_every, r.seg_ext, seg, 90);
}

// CT slice k: its own (larger) pixels, no drift, HU + 1024 stored, 16-bit; at every
// ct_every-th colour slice only.
void render_ct(const PresetRun& r, int k, const SliceParams& params) {
  if (k % r.options.ct_every != 0) return;
  const int W = r.plan.preset.width, H = r.plan.preset.height, C = r.plan.preset.ct_size;
  const double cx = (W - 1) * 0.5, cy = (H - 1) * 0.5, cct = (C - 1) * 0.5;
  cv::Mat ct(C, C, CV_16UC1);
  Sample sample;
  const double th = r.plan.ct_rot * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
  const double s = r.plan.ct_scale;
  Random noise(mix64(r.options.seed ^ (0x2545f4914f6cdd1dull * std::uint64_t(k + 1))));
  for (int v = 0; v < C; ++v) {
    auto* row = ct.ptr<std::uint16_t>(v);
    for (int u = 0; u < C; ++u) {
      const double du = u - cct, dv = v - cct;
      const double qx = cx + s * (cs * du - sn * dv) + r.plan.ct_dx;
      const double qy = cy + s * (sn * du + cs * dv) + r.plan.ct_dy;
      r.model.eval(params, qx, qy, s, false, true, sample);
      float gauss[4];
      noise.normal4(r.gaussian, gauss);
      const double hu = sample.hu + kCtNoiseHu * gauss[0];
      row[u] = static_cast<std::uint16_t>(std::clamp(std::lround(hu + 1024.0), 0L, 4095L));
    }
  }
  r.folder.write_ct(k / r.options.ct_every, ct);
}

// truth/transforms.json (docs/ARCHITECTURE.md "Slice transforms"), by the phantom's own writer,
// plus its extras: per-slice "gain", the camera offset, noise levels, preset and seed.
void write_preset_transforms(const PresetRun& r) {
  const Plan& plan = r.plan;
  const int H = plan.preset.height;
  TruthTransforms tt;
  tt.width = plan.preset.width, tt.height = H, tt.frame = "ct", tt.has_ct = true;
  tt.ct_scale = plan.ct_scale, tt.ct_rotation_deg = plan.ct_rot;
  tt.ct_dx_px = plan.ct_dx, tt.ct_dy_px = plan.ct_dy;
  for (int k = 0; k < plan.slices; ++k) {
    const SliceTruth& st = plan.truth[k];
    TruthSlice s;
    s.index = k, s.number = k, s.file = r.folder.rgb_name(k, r.rgb_ext);
    s.dx_px = st.dx, s.dy_px = st.dy, s.rotation_deg = st.rot;
    s.jump = st.jump, s.black = st.black, s.duplicate_of = st.duplicate_of, s.gain = st.gain;
    tt.slices.push_back(s);
  }
  if (!plan.block_starts.empty()) {
    tt.extra["block_starts"] = plan.block_starts;
    tt.extra["block_gains"] = plan.block_gains;
  }
  if (!r.truth_sample.empty()) {
    // A streamed folder: the truth of these slices only, in truth/sample/.
    tt.extra["truth_every"] = r.options.truth_every;
    tt.extra["truth_sample"] = r.truth_sample;
  }
  tt.extra["camera_offset"] = {
      {"rotation_deg", plan.cam_rot}, {"dx_px", plan.cam_dx}, {"dy_px", plan.cam_dy}};
  tt.extra["noise_sigma"] = kNoiseSigma;
  tt.extra["ct_noise_hu"] = kCtNoiseHu;
  tt.extra["preset"] = plan.preset.name;
  if (plan.anatomy.limbs) {
    // The CT's table on the output grid (rows, y down; top edge, bottom edge), for scoring
    // holder pixels in a mask.
    const double top = (H - 1) * 0.5 + r.model.slice(0).table_top * H * 0.5;
    tt.extra["table_rows_px"] = {top, top + plan.anatomy.table_px};
  }
  tt.extra["seed"] = r.options.seed;
  tt.extra["fiducials"] = plan.anatomy.fiducials;
  tt.extra["drift"] = r.options.drift;
  r.folder.write_truth_transforms(tt);
}

// A ready config, written through the pipeline's own config writer (one writer of the schema);
// with CT the output frame is defined by the CT (register.output_frame).
void write_preset_config(const PresetRun& r) {
  const PhantomPreset& p = r.plan.preset;
  const PhantomOptions& options = r.options;
  pipeline::Config config = r.folder.base_config("phantom-" + p.name, r.rgb_ext,
                                                 {p.ct_pixel_mm, p.ct_pixel_mm}, r.seg_ext);
  if (options.rgb_raw) config.rgb.raw = r.raw;
  if (options.ct_every > 1) config.ct->slice_spacing_mm = options.ct_every * p.slice_mm;
  pipeline::SegSource& seg = *config.seg;
  seg.mode = "colour";
  seg.tolerance = options.seg_jpeg ? 48 : 24;
  seg.strict = false;
  if (options.seg_every > 1) seg.slice_spacing_mm = options.seg_every * p.slice_mm;
  config.registration.method = "phase+ecc";
  config.registration.ecc_scale = 0.5;
  config.registration.jump_px = 6.0;
  config.registration.output_frame = r.plan.output_frame;
  config.mask.hu_threshold = -400;
  config.mask.opening_px = 1;
  config.mask.refine_gel = true;
  r.folder.write_config(config);
}

// What the folder will take on disk, about: the colour slices (raw: exact; PNG: as raw, an upper
// bound for noisy colour), the CT slices (16-bit PNG, at most 2 bytes a pixel), the segmentation
// (flat colours: PNG a sixteenth of raw, JPEG a quarter) and the truth (the volumes, or the sampled
// slices' PNGs at most 3 bytes a pixel).
std::uint64_t estimate_bytes(const Plan& plan, const PhantomOptions& options) {
  const PhantomPreset& p = plan.preset;
  const std::uint64_t plane = std::uint64_t(p.width) * p.height, n = std::uint64_t(plan.slices);
  const std::uint64_t ct_slices = (n + options.ct_every - 1) / options.ct_every;
  const std::uint64_t seg_slices = (n + options.seg_every - 1) / options.seg_every;
  std::uint64_t bytes = n * plane * 3;
  bytes += ct_slices * std::uint64_t(p.ct_size) * p.ct_size * 2;
  bytes += seg_slices * plane * 3 / (options.seg_jpeg ? 4 : 16);
  if (options.truth_every >= 2)
    bytes += ((n + options.truth_every - 1) / options.truth_every) * plane * 3;
  else
    bytes += n * plane * 10;
  return bytes + 64 * 1024;  // palette, config, transforms
}

// Leftovers of an earlier run with another preset, slice count or format.
void remove_leftovers(const PresetRun& r) {
  const PhantomOptions& options = r.options;
  const int digits = r.plan.digits;
  std::vector<std::string> keep_rgb, keep_seg, keep_ct;
  for (int k = 0; k < r.plan.slices; ++k) {
    keep_rgb.push_back(numbered("rgb", k, digits, r.rgb_ext));
    if (k % options.seg_every == 0)
      keep_seg.push_back(numbered("seg", k / options.seg_every, digits, r.seg_ext));
    if (k % options.ct_every == 0)
      keep_ct.push_back(numbered("ct", k / options.ct_every, digits, ".png"));
  }
  const std::string& out_dir = r.folder.dir();
  remove_stale(out_dir + "/rgb", std::regex("rgb_[0-9]+\\.(png|raw)"), keep_rgb);
  remove_stale(out_dir + "/seg", std::regex("seg_[0-9]+\\.(png|jpg)"), keep_seg);
  remove_stale(out_dir + "/ct", std::regex("ct_[0-9]+\\.png"), keep_ct);
  std::vector<std::string> keep_sample;
  for (int k : r.truth_sample) {
    keep_sample.push_back(numbered("mask", k, digits, ".png"));
    keep_sample.push_back(numbered("labels", k, digits, ".png"));
  }
  std::error_code ec;
  if (fs::is_directory(out_dir + "/truth/sample", ec))
    remove_stale(out_dir + "/truth/sample", std::regex("(mask|labels)_[0-9]+\\.png"), keep_sample);
  if (!r.truth_sample.empty()) {
    // A streamed folder holds no truth volume: an earlier folder's would not match its slices.
    for (const char* v : {"rgb", "ct", "mask", "labels", "seg_labels"})
      fs::remove(out_dir + "/truth/" + v + ".nrrd", ec);
  }
}

}  // namespace

PhantomSummary make_phantom(const std::string& out_dir, const PhantomOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  const Plan plan = make_plan(options);
  const PhantomPreset& p = plan.preset;
  const int W = p.width, H = p.height, N = plan.slices;
  const bool streamed = options.truth_every >= 2;
  const std::uint64_t needed = estimate_bytes(plan, options);
  check_free_space(out_dir, needed, options.keep_free_bytes);
  const Model model(W, H, N, options.seed, plan.anatomy);
  const GaussianTable gaussian;
  PhantomFolder folder(out_dir, W, H, N, {p.pixel_mm, p.pixel_mm, p.slice_mm}, plan.digits,
                       !streamed);
  PresetRun run{plan,
                options,
                model,
                gaussian,
                folder,
                options.rgb_raw ? ".raw" : ".png",
                options.seg_jpeg ? ".jpg" : ".png",
                RawLayout{},
                {}};
  run.raw.width = W, run.raw.height = H, run.raw.channels = 3, run.raw.planar = true;
  run.raw.bits = 8;
  if (streamed) {
    for (int k = 0; k < N; k += options.truth_every)
      run.truth_sample.push_back(k);
  }

  Progress progress("vispack-phantom", N, "slices", options.quiet);
  parallel_for(N, resolve_threads(options.threads), [&](std::int64_t kk) {
    const int k = static_cast<int>(kk);
    const SliceParams params = model.slice(k);
    if (!streamed) {
      render_truth(run, folder.truth_planes(k), params);
      render_observed(run, k, params, folder.truth_seg_labels(k));
    } else {
      // A streamed folder holds one slice's truth at a time, for the sampled slices only.
      if (k % options.truth_every == 0) {
        const std::size_t plane = std::size_t(W) * H;
        std::vector<std::uint8_t> rgb(plane * 3), mask(plane);
        std::vector<std::int16_t> ct(plane);
        std::vector<std::uint16_t> labels(plane);
        render_truth(run, TruthPlanes{rgb.data(), ct.data(), mask.data(), labels.data()}, params);
        folder.write_truth_sample(k, mask.data(), labels.data());
      }
      render_observed(run, k, params, nullptr);
    }
    render_ct(run, k, params);
    progress.advance();
  });
  progress.finish();

  folder.write_truth_volumes();
  write_preset_transforms(run);
  std::vector<PaletteEntry> palette;
  for (int id = 1; id < kLabelCount; ++id)
    palette.push_back({id, label_info(id).name, label_info(id).palette});
  folder.write_palette(palette);
  write_preset_config(run);
  remove_leftovers(run);

  PhantomSummary summary;
  summary.width = W;
  summary.height = H;
  summary.slices = N;
  summary.ct_size = p.ct_size;
  summary.jump_slice = plan.jump;
  summary.black_slice = plan.black;
  summary.duplicate_slice = plan.duplicate;
  summary.jump_slices = plan.jumps;
  summary.black_slices = plan.blacks;
  summary.truth_sample = run.truth_sample;
  summary.estimated_bytes = needed;
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return summary;
}

}  // namespace vispack::phantom

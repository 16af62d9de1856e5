// Pair estimates (phase correlation + ECC) and the per-slice pair records. See register/pair.h.
#include "vispack/pipeline/register/pair.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <map>
#include <optional>
#include <utility>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/math_constants.h"
#include "vispack/common/parallel.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/ecc.h"
#include "vispack/pipeline/register/rotation_search.h"

namespace vispack::pipeline {
namespace {

constexpr int kLookBack = 4;  // edges reach back over at most 4 slices
// Fine ECC stops when the correlation improves by less than this per iteration: from the
// coarse estimate (within ~0.1 coarse px) it converges in a few iterations.
constexpr double kFineEps = 1e-5;
// ... and after an update that moves no pixel by more than this many full-resolution pixels
// (EccOptions::min_step_px; 0.01 px of the fine level at ecc_scale 0.5): a tenth or less of the
// pair's own error, and one pass over the image less on most pairs (docs/BENCHMARKS.md
// "Register stage: CPU per slice").
constexpr double kFineStepFullPx = 0.02;
// A pair whose middle-level correlation is under kDissimilarRho shows different anatomy more than
// the same tissue moved: its ECC creeps a few tenths of a pixel an iteration towards wherever the
// anatomy pulls. Its fine pass has kDissimilarFineIterations; one that has not converged by then
// is a failure, as a path that ran past the reach is (docs/BENCHMARKS.md "Register stage: CPU
// per slice").
constexpr double kDissimilarRho = 0.9;
constexpr int kDissimilarFineIterations = 10;

// ECC at one level; `m` (full-resolution j→k matrix) is updated in place on success. Returns
// rho, or nullopt where ECC fails (m unchanged; `last`, when given, then holds the last iterate
// as a full-resolution matrix). `too_far` (optional) is given each iterate as a full-resolution
// matrix; true fails the refinement at once (EccOptions::diverged); `give_up`: EccOptions::give_up.
std::optional<double> ecc_level(const cv::Mat& from, const cv::Mat& to, double scale,
                                cv::Matx23d& m, int iterations, double eps,
                                const std::function<bool(const cv::Matx23d&)>& too_far = {},
                                double min_step_full_px = 0.0,
                                std::function<bool(double, int)> give_up = {},
                                cv::Matx23d* last = nullptr) {
  cv::Matx23d ms = scale_affine(m, scale);
  EccOptions options;
  options.iterations = iterations;
  options.eps = eps;
  options.min_step_px = min_step_full_px * scale;
  options.blur_size = 1;  // the frames are pre-blurred (prepare_frame)
  if (too_far)
    options.diverged = [&](const cv::Matx23d& w) { return too_far(unscale_affine(w, scale)); };
  options.give_up = std::move(give_up);
  const std::optional<double> rho = ecc_euclidean(from, to, ms, options);
  if (rho) m = unscale_affine(ms, scale);
  if (last) *last = unscale_affine(ms, scale);
  return rho;
}

// Step 3 of estimate_pair: ECC at ecc_scale from `m` (full-resolution matrix of `start`).
// On success sets est.relative, est.quality (the correlation) and est.ecc_ok; a refinement that
// moves more than 4 coarse pixels from `start` has diverged and counts as a failure.
bool refine_fine(const RegisterFrame& from, const RegisterFrame& to, const RegisterOptions& options,
                 const Rigid& start, cv::Matx23d m, PairEstimate& est) {
  const cv::Point2d centre = image_centre(from.full_size);
  const double reach = 4.0 / from.coarse_scale;
  auto travel = [&](const Rigid& r) {  // how far an estimate lies from `start`
    return rigid_motion_px(
        {r.rotation_deg - start.rotation_deg, r.dx_px - start.dx_px, r.dy_px - start.dy_px},
        from.full_size);
  };
  // An iterate twice beyond the reach ends the refinement: on slices whose anatomy differs the
  // iteration creeps on for tens of pixels, to be rejected below (docs/BENCHMARKS.md "Register
  // stage: CPU per slice").
  auto too_far = [&](const cv::Matx23d& full) {
    return travel(rigid_from_matrix(full, centre)) >= kEccRunawayFactor * reach;
  };
  // A first pass at the middle level (a quarter of the pixels): the fine pass then starts
  // where the middle one ended, a few fine iterations from its own optimum. A pair that shows
  // itself dissimilar there (a correlation under kDissimilarRho), or whose middle pass fails,
  // gets the capped fine pass; a dissimilar middle pass still moving at its
  // kDissimilarFineIterations-th update is not followed further: the capped fine pass starts from
  // that iterate (docs/BENCHMARKS.md "Register stage: CPU per slice").
  int fine_iterations = std::max(1, options.ecc_iterations);
  bool capped = false;
  if (!from.middle.empty() && from.middle.size() == to.middle.size()) {
    cv::Matx23d mm = m, last = m;
    bool crept = false;
    auto creeping = [&](double rho, int update) {
      return crept = rho < kDissimilarRho && update >= kDissimilarFineIterations;
    };
    const std::optional<double> rho_middle =
        ecc_level(from.middle, to.middle, from.middle_scale, mm, fine_iterations, kFineEps, too_far,
                  kFineStepFullPx, creeping, &last);
    if (rho_middle) m = mm;
    if (crept) m = last;
    if ((!rho_middle || *rho_middle < kDissimilarRho) &&
        fine_iterations > kDissimilarFineIterations)
      fine_iterations = kDissimilarFineIterations, capped = true;
  }
  // A capped pass that is still moving at its last update has not converged.
  int updates = 0;
  auto too_far_or_unconverged = [&](const cv::Matx23d& full) {
    return too_far(full) || (capped && ++updates >= fine_iterations);
  };
  const std::optional<double> rho =
      ecc_level(from.fine, to.fine, from.fine_scale, m, fine_iterations, kFineEps,
                too_far_or_unconverged, kFineStepFullPx);
  if (!rho) return false;  // ECC did not converge, or ran away
  const Rigid refined = rigid_from_matrix(m, centre);
  if (travel(refined) < reach) {
    est.relative = refined;
    est.quality = std::clamp(*rho, 0.0, 1.0);
    est.ecc_ok = true;
    return true;
  }
  return false;
}

// Step 1 of estimate_pair, the coarse search: phase correlation at a rotation φ of the `to`
// slice. The phase-correlation peak favours interpolated (smoother) images, so candidates are
// ranked by the normalised correlation of the aligned images instead. Holds references to both
// frames.
class CoarseSearch {
 public:
  struct Candidate {
    double angle, response, score;
    cv::Point2d shift;  // coarse pixels, rotated frame: W(x) = c + R(φ)(x + s − c)
  };

  CoarseSearch(const RegisterFrame& from, const RegisterFrame& to)
      : from_(from),
        to_(to),
        centre_(image_centre(from.full_size)),
        cc_(image_centre(from.coarse.size())),
        inner_(from.coarse.cols / 10, from.coarse.rows / 10, from.coarse.cols * 8 / 10,
               from.coarse.rows * 8 / 10),
        from_inner_(from.coarse(inner_)) {
    cv::createHanningWindow(window_, from.coarse.size(), CV_32F);
    // cv::phaseCorrelate multiplies its inputs by the window in place (OpenCV 4.6), so the
    // window is applied here to copies and no window is passed.
    from_windowed_ = from.coarse.mul(window_);
  }

  Candidate evaluate(double angle) const {
    Candidate cand{angle, 0.0, -2.0, {}};
    cv::Mat rotated = rotate_about_centre(to_.coarse, angle);
    cand.shift =
        cv::phaseCorrelate(from_windowed_, rotated.mul(window_), cv::noArray(), &cand.response);
    const double a = angle * kPi / 180.0;
    const cv::Point2d rs(std::cos(a) * cand.shift.x - std::sin(a) * cand.shift.y,
                         std::sin(a) * cand.shift.x + std::cos(a) * cand.shift.y);
    cv::Mat aligned;
    cv::warpAffine(to_.coarse, aligned, cv::Mat(rigid_matrix({angle, rs.x, rs.y}, cc_)),
                   from_.coarse.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                   cv::BORDER_REPLICATE);
    cv::Mat score;
    cv::matchTemplate(aligned(inner_), from_inner_, score, cv::TM_CCOEFF_NORMED);
    cand.score = std::isfinite(score.at<float>(0, 0)) ? score.at<float>(0, 0) : -1.0;
    return cand;
  }

  // The sweep over −10°..10°, refined by half steps and a parabola (register/rotation_search.h).
  Candidate sweep() const {
    return sweep_rotation([this](double angle) { return evaluate(angle); });
  }

  // A candidate as the full-resolution relative transform.
  Rigid to_rigid(const Candidate& c) const {
    const double a = c.angle * kPi / 180.0;
    const cv::Point2d rs(std::cos(a) * c.shift.x - std::sin(a) * c.shift.y,
                         std::sin(a) * c.shift.x + std::cos(a) * c.shift.y);
    return rigid_from_matrix(
        unscale_affine(rigid_matrix({c.angle, rs.x, rs.y}, cc_), from_.coarse_scale), centre_);
  }

  // Coarse ECC from a phase estimate; returns rho (−1 on failure) and updates `m`.
  double coarse_ecc(cv::Matx23d& m) const {
    return ecc_level(from_.coarse, to_.coarse, from_.coarse_scale, m, 30, 1e-4).value_or(-1.0);
  }

 private:
  const RegisterFrame& from_;
  const RegisterFrame& to_;
  cv::Point2d centre_, cc_;
  cv::Rect inner_;
  cv::Mat from_inner_, window_, from_windowed_;
};

}  // namespace

PairEstimate estimate_pair(const RegisterFrame& from, const RegisterFrame& to,
                           const RegisterOptions& options, const Rigid* initial) {
  if (from.full_size != to.full_size || from.fine.size() != to.fine.size())
    throw Error(cat("estimate_pair: slices differ in size (", from.full_size.width, "x",
                    from.full_size.height, " and ", to.full_size.width, "x", to.full_size.height,
                    ")"));
  PairEstimate est;
  if (options.method == "none") {
    est.quality = 1.0;
    est.ecc_ok = true;
    return est;
  }
  const cv::Point2d centre = image_centre(from.full_size);
  // A good starting estimate (a skip edge composed from two neighbour edges): the fine step
  // alone; the full search only if that fails.
  if (initial && options.method == "phase+ecc") {
    PairEstimate quick;
    if (refine_fine(from, to, options, *initial, rigid_matrix(*initial, centre), quick))
      return quick;
  }
  // 1. Coarse: phase correlation (CoarseSearch), the sweep for method "phase", 0° otherwise.
  const CoarseSearch search(from, to);
  using Candidate = CoarseSearch::Candidate;
  Candidate best = options.method == "phase" ? search.sweep() : search.evaluate(0.0);
  est.response = std::clamp(best.response, 0.0, 1.0);
  est.relative = search.to_rigid(best);
  est.quality = std::clamp(best.score, 0.0, 1.0);
  if (options.method == "phase") return est;

  // 2. Coarse ECC from the 0° estimate; the sweep only when that is not confident.
  constexpr double kConfident = 0.85;
  Rigid start = est.relative;
  cv::Matx23d m = rigid_matrix(start, centre);
  double rho_coarse = search.coarse_ecc(m);
  if (rho_coarse < kConfident) {
    Candidate swept = search.sweep();
    cv::Matx23d m2 = rigid_matrix(search.to_rigid(swept), centre);
    const double rho2 = search.coarse_ecc(m2);
    if (rho2 > rho_coarse || (rho_coarse < 0 && swept.score > best.score)) {
      best = swept;
      start = search.to_rigid(swept);
      m = m2;
      rho_coarse = rho2;
      est.response = std::clamp(best.response, 0.0, 1.0);
      est.relative = start;
      est.quality = std::clamp(best.score, 0.0, 1.0);
    }
  }
  if (rho_coarse < 0) {
    m = rigid_matrix(start, centre);  // coarse ECC failed: from the phase estimate
  } else {
    start = rigid_from_matrix(m, centre);
    est.relative = start;
  }

  // 3. ECC at ecc_scale.
  if (!refine_fine(from, to, options, start, m, est)) est.quality = std::min(est.quality, 0.5);
  return est;
}

nlohmann::json to_json(const SlicePairs& p) {
  nlohmann::json edges = nlohmann::json::array();
  for (const auto& e : p.edges)
    edges.push_back({{"from", e.from},
                     {"to", e.to},
                     {"rotation_deg", e.relative.rotation_deg},
                     {"dx_px", e.relative.dx_px},
                     {"dy_px", e.relative.dy_px},
                     {"weight", e.weight}});
  nlohmann::json fiducials = nlohmann::json::array();
  for (const auto& f : p.fiducials)
    fiducials.push_back({f.x, f.y});
  return {{"index", p.index},
          {"black", p.black},
          {"duplicate_of", p.duplicate_of ? nlohmann::json(*p.duplicate_of) : nlohmann::json()},
          {"pixel_hash", hex64(p.pixel_hash)},
          {"quality", p.quality},
          {"edges", edges},
          {"fiducials", fiducials},
          {"anchor", p.anchor ? to_json(*p.anchor) : nlohmann::json()}};
}

SlicePairs slice_pairs_from_json(const nlohmann::json& j, const std::string& what) {
  try {
    SlicePairs p;
    p.index = j.at("index").get<int>();
    p.black = j.at("black").get<bool>();
    if (!j.at("duplicate_of").is_null()) p.duplicate_of = j.at("duplicate_of").get<int>();
    p.pixel_hash = std::stoull(j.at("pixel_hash").get<std::string>(), nullptr, 16);
    p.quality = j.at("quality").get<double>();
    for (const auto& e : j.at("edges")) {
      PairEdge edge;
      edge.from = e.at("from").get<int>();
      edge.to = e.at("to").get<int>();
      edge.relative = {e.at("rotation_deg").get<double>(), e.at("dx_px").get<double>(),
                       e.at("dy_px").get<double>()};
      edge.weight = e.at("weight").get<double>();
      if (!(edge.weight > 0.0) || edge.to != p.index || edge.from >= edge.to || edge.from < 0)
        throw FormatError("bad edge");
      p.edges.push_back(edge);
    }
    if (j.contains("fiducials")) {
      for (const auto& f : j.at("fiducials")) {
        const cv::Point2d pt(f.at(0).get<double>(), f.at(1).get<double>());
        if (!std::isfinite(pt.x) || !std::isfinite(pt.y)) throw FormatError("bad fiducial");
        p.fiducials.push_back(pt);
      }
    }
    if (j.contains("anchor") && !j.at("anchor").is_null())
      p.anchor = anchor_from_json(j.at("anchor"), what);
    return p;
  } catch (const std::exception& e) {
    throw FormatError(cat(what, ": malformed pair record: ", e.what()));
  }
}

namespace {

// compute_pairs' state between blocks: the prepared frames of the look-back window and the
// record of every prepared slice (black / duplicate status, edges, anchor).
struct PairState {
  std::map<int, RegisterFrame> frames;
  std::map<int, SlicePairs> status;
};

struct PairJob {
  int from, to;
};

// Prepares the frames of slices [block, block_end) (in parallel) and records each one's black
// and duplicate status (a duplicate: the same pixels as a usable slice within kLookBack).
void prepare_block(PairState& st, int block, int block_end,
                   const std::function<RegisterFrame(int)>& frame, int threads) {
  std::vector<RegisterFrame> prepared(std::size_t(block_end - block));
  parallel_for(block_end - block, threads,
               [&](std::int64_t i) { prepared[std::size_t(i)] = frame(block + int(i)); });
  for (int k = block; k < block_end; ++k) {
    RegisterFrame& f = prepared[std::size_t(k - block)];
    SlicePairs s;
    s.index = k;
    s.black = f.black;
    s.pixel_hash = f.pixel_hash;
    s.quality = s.black ? 0.0 : 1.0;
    s.fiducials = f.fiducials;
    if (!s.black) {
      for (int j = k - 1; j >= std::max(0, k - kLookBack); --j) {
        auto it = st.status.find(j);
        if (it == st.status.end() || it->second.black) continue;
        if (it->second.pixel_hash == s.pixel_hash && st.frames.at(j).full_size == f.full_size) {
          s.duplicate_of = it->second.duplicate_of ? *it->second.duplicate_of : j;
          break;
        }
      }
    }
    st.status[k] = s;
    st.frames[k] = std::move(f);
  }
}

// The edges of the block's usable slices: each one's edge from its previous usable slice
// (`nearest`), and from the one before that (`skip`, only for slices from `first` on). The
// look-back slices before `first` get their nearest edges too (not returned): the skip edges
// into `first` start from them exactly as in an unsharded run, so shards reproduce the
// unsharded records.
void plan_edges(const PairState& st, int lo, int first, int block, int block_end,
                std::vector<PairJob>& nearest, std::vector<PairJob>& skip) {
  for (int k = std::max(lo, block); k < block_end; ++k) {
    const SlicePairs& s = st.status.at(k);
    if (s.black || s.duplicate_of) continue;
    int found = 0;
    for (int j = k - 1; j >= std::max(lo, k - kLookBack) && found < 2; --j) {
      const SlicePairs& p = st.status.at(j);
      if (p.black || p.duplicate_of) continue;
      if (found == 0) {
        nearest.push_back({j, k});
      } else if (k >= first) {
        skip.push_back({j, k});
      }
      ++found;
    }
  }
}

void record_edge(PairState& st, const PairJob& job, const PairEstimate& r) {
  SlicePairs& s = st.status[job.to];
  const bool is_nearest = s.edges.empty();  // nearest edges are recorded first
  s.edges.push_back({job.from, job.to, r.relative, r.ecc_ok ? 1.0 : 0.05});
  if (is_nearest) s.quality = r.quality;
}

// A skip edge's start: the measured edges i→k and j→i (i = k's nearest usable predecessor)
// composed, where both were measured well.
std::optional<Rigid> composed_start(const PairState& st, const PairJob& job) {
  const SlicePairs& sk = st.status.at(job.to);
  if (sk.edges.empty() || sk.edges[0].weight < 1.0) return std::nullopt;
  const int i = sk.edges[0].from;
  auto it = st.status.find(i);
  if (it == st.status.end() || it->second.edges.empty()) return std::nullopt;
  const PairEdge& ji = it->second.edges[0];
  if (ji.from != job.from || ji.weight < 1.0) return std::nullopt;
  const cv::Point2d c = image_centre(st.frames.at(job.to).full_size);
  return rigid_from_matrix(
      compose_affine(rigid_matrix(sk.edges[0].relative, c), rigid_matrix(ji.relative, c)), c);
}

// Measures the edges (in parallel) and records them: first every nearest edge (the full
// search), then the skip edges, each started from the composition of two measured neighbour
// edges where there is one.
void measure_edges(PairState& st, const std::vector<PairJob>& nearest,
                   const std::vector<PairJob>& skip, const RegisterOptions& options, int threads) {
  std::vector<PairEstimate> results(nearest.size());
  parallel_for(std::int64_t(nearest.size()), threads, [&](std::int64_t i) {
    const PairJob& job = nearest[std::size_t(i)];
    results[std::size_t(i)] = estimate_pair(st.frames.at(job.from), st.frames.at(job.to), options);
  });
  for (std::size_t i = 0; i < nearest.size(); ++i)
    record_edge(st, nearest[i], results[i]);
  results.assign(skip.size(), PairEstimate{});
  parallel_for(std::int64_t(skip.size()), threads, [&](std::int64_t i) {
    const PairJob& job = skip[std::size_t(i)];
    const std::optional<Rigid> start = composed_start(st, job);
    results[std::size_t(i)] = estimate_pair(st.frames.at(job.from), st.frames.at(job.to), options,
                                            start ? &*start : nullptr);
  });
  for (std::size_t i = 0; i < skip.size(); ++i)
    record_edge(st, skip[i], results[i]);
}

// The CT anchors of the usable slices [from, to) (in parallel).
void measure_anchors(
    PairState& st, int from, int to,
    const std::function<std::optional<AnchorEstimate>(int, const RegisterFrame&)>& anchor,
    int threads) {
  std::vector<int> todo;
  for (int k = from; k < to; ++k)
    if (!st.status[k].black) todo.push_back(k);
  std::vector<std::optional<AnchorEstimate>> found(todo.size());
  parallel_for(std::int64_t(todo.size()), threads, [&](std::int64_t i) {
    const int k = todo[std::size_t(i)];
    found[std::size_t(i)] = anchor(k, st.frames.at(k));
  });
  for (std::size_t i = 0; i < todo.size(); ++i)
    st.status[todo[i]].anchor = found[i];
}

}  // namespace

std::vector<SlicePairs> compute_pairs(
    int first, int last, const std::function<RegisterFrame(int)>& frame,
    const RegisterOptions& options, int threads,
    const std::function<std::optional<AnchorEstimate>(int, const RegisterFrame&)>& anchor) {
  std::vector<SlicePairs> out;
  if (last <= first) return out;
  const int lo = std::max(0, first - kLookBack);
  // Frames are prepared in blocks so memory stays bounded by the block (plus the look-back).
  constexpr int kBlock = 32;
  PairState st;
  out.reserve(std::size_t(last - first));
  for (int block = lo; block < last; block += kBlock) {
    const int block_end = std::min(last, block + kBlock);
    prepare_block(st, block, block_end, frame, threads);
    // Edges of the block's slices inside [first, last).
    std::vector<PairJob> nearest, skip;
    plan_edges(st, lo, first, block, block_end, nearest, skip);
    measure_edges(st, nearest, skip, options, threads);
    // CT anchors of the block's slices inside [first, last).
    if (anchor) measure_anchors(st, std::max(first, block), block_end, anchor, threads);
    for (int k = std::max(first, block); k < block_end; ++k)
      out.push_back(st.status[k]);
    // Keep only the look-back window of frames.
    while (!st.frames.empty() && st.frames.begin()->first < block_end - kLookBack)
      st.frames.erase(st.frames.begin());
  }
  return out;
}

}  // namespace vispack::pipeline

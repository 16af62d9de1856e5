// The least-squares solves of the stack. See register/solve.h.
#include "vispack/pipeline/register/solve.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <map>
#include <queue>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/pipeline/imaging/transforms.h"

namespace vispack::pipeline {
namespace {

// ---- banded symmetric positive-definite solver (normal equations of the pair graph) ----
class BandedSpd {
 public:
  BandedSpd(int n, int band) : n_(n), band_(band), a_(std::size_t(n) * (band + 1), 0.0) {}
  int size() const { return n_; }
  void add(int i, int j, double v) {  // symmetric entry (i, j) += v, |i − j| <= band
    if (i < j) std::swap(i, j);
    a_[std::size_t(i) * (band_ + 1) + (i - j)] += v;
  }
  // In-place Cholesky (L stored in the band).
  void factor() {
    for (int i = 0; i < n_; ++i) {
      for (int j = std::max(0, i - band_); j <= i; ++j) {
        double s = at(i, j);
        for (int k = std::max(0, i - band_); k < j; ++k)
          s -= at(i, k) * at(j, k);
        if (i == j) {
          at(i, i) = std::sqrt(std::max(s, 1e-300));
        } else {
          at(i, j) = s / at(j, j);
        }
      }
    }
  }
  // Forward/back substitution with the factor.
  std::vector<double> solve(std::vector<double> y) const {
    for (int i = 0; i < n_; ++i) {
      for (int k = std::max(0, i - band_); k < i; ++k)
        y[i] -= at(i, k) * y[k];
      y[i] /= at(i, i);
    }
    for (int i = n_ - 1; i >= 0; --i) {
      for (int k = i + 1; k <= std::min(n_ - 1, i + band_); ++k)
        y[i] -= at(k, i) * y[k];
      y[i] /= at(i, i);
    }
    return y;
  }

 private:
  double& at(int i, int j) { return a_[std::size_t(i) * (band_ + 1) + (i - j)]; }
  double at(int i, int j) const { return a_[std::size_t(i) * (band_ + 1) + (i - j)]; }
  int n_, band_;
  std::vector<double> a_;
};

// Normal equations [[B, C], [Cᵀ, D]] [x; y] = [b; e]: B banded over the first n unknowns (the
// slices), C and D dense for the m border unknowns (free frames). Solved by the Schur
// complement: S = D − Cᵀ B⁻¹ C (m × m), y = S⁻¹ (e − Cᵀ B⁻¹ b), x = B⁻¹ (b − C y).
class BorderedSystem {
 public:
  BorderedSystem(int n, int band, int m)
      : n_(n),
        m_(m),
        b_mat_(n, band),
        c_(std::size_t(n) * m, 0.0),
        d_(std::size_t(m) * m, 0.0),
        rhs_(std::size_t(n + m), 0.0) {}
  void add(int i, int j, double v) {  // symmetric entry (i, j) += v (i ≠ j: both triangles)
    if (i < n_ && j < n_) {
      b_mat_.add(i, j, v);
    } else if (i >= n_ && j >= n_) {
      d_[std::size_t(i - n_) * m_ + (j - n_)] += v;
      if (i != j) d_[std::size_t(j - n_) * m_ + (i - n_)] += v;
    } else {
      if (i >= n_) std::swap(i, j);
      c_[std::size_t(i) * m_ + (j - n_)] += v;
    }
  }
  void add_rhs(int i, double v) { rhs_[std::size_t(i)] += v; }
  std::vector<double> solve() {
    b_mat_.factor();
    std::vector<double> b(rhs_.begin(), rhs_.begin() + n_);
    std::vector<double> x = b_mat_.solve(b);
    if (m_ == 0) return x;
    // X = B⁻¹ C, column by column.
    std::vector<std::vector<double>> xc(static_cast<std::size_t>(m_));
    for (int c = 0; c < m_; ++c) {
      std::vector<double> col(static_cast<std::size_t>(n_));
      for (int i = 0; i < n_; ++i)
        col[std::size_t(i)] = c_[std::size_t(i) * m_ + c];
      xc[std::size_t(c)] = b_mat_.solve(col);
    }
    cv::Mat s(m_, m_, CV_64F), r(m_, 1, CV_64F);
    for (int a = 0; a < m_; ++a) {
      double ra = rhs_[std::size_t(n_ + a)];
      for (int i = 0; i < n_; ++i)
        ra -= c_[std::size_t(i) * m_ + a] * x[std::size_t(i)];
      r.at<double>(a) = ra;
      for (int c = 0; c < m_; ++c) {
        double v = d_[std::size_t(a) * m_ + c];
        for (int i = 0; i < n_; ++i)
          v -= c_[std::size_t(i) * m_ + a] * xc[std::size_t(c)][std::size_t(i)];
        s.at<double>(a, c) = v;
      }
    }
    cv::Mat y;
    cv::solve(s, r, y, cv::DECOMP_SVD);
    for (int i = 0; i < n_; ++i)
      for (int c = 0; c < m_; ++c)
        x[std::size_t(i)] -= xc[std::size_t(c)][std::size_t(i)] * y.at<double>(c);
    for (int c = 0; c < m_; ++c)
      x.push_back(y.at<double>(c));
    return x;
  }

 private:
  int n_, m_;
  BandedSpd b_mat_;
  std::vector<double> c_, d_, rhs_;
};

}  // namespace

std::vector<Rigid> solve_chain(int n, const std::vector<PairEdge>& edges, int free_nodes) {
  const int m = std::max(free_nodes, 0);
  const int total = std::max(n, 0) + m;
  std::vector<Rigid> out(std::size_t(std::max(total, 0)));
  if (n <= 1 && m == 0) return out;
  int band = 1;
  std::vector<std::vector<int>> adjacency(static_cast<std::size_t>(total));
  for (const auto& e : edges) {
    if (e.from < 0 || e.to < 0 || e.from >= total || e.to >= total || e.from == e.to)
      throw Error(cat("solve_chain: edge ", e.from, "->", e.to, " outside the stack of ", n,
                      " slices and ", m, " free frames"));
    if (e.from < n && e.to < n) band = std::max(band, std::abs(e.to - e.from));
    adjacency[std::size_t(e.from)].push_back(e.to);
    adjacency[std::size_t(e.to)].push_back(e.from);
  }
  // Nodes connected to the reference.
  std::vector<bool> reached(static_cast<std::size_t>(total), false);
  std::queue<int> queue;
  reached[0] = true;
  queue.push(0);
  while (!queue.empty()) {
    int i = queue.front();
    queue.pop();
    for (int j : adjacency[std::size_t(i)])
      if (!reached[std::size_t(j)]) reached[std::size_t(j)] = true, queue.push(j);
  }
  // A tiny prior pins unreached nodes (and keeps the system positive definite).
  constexpr double kPrior = 1e-9;
  // Rotations: θ_to − θ_from = φ; θ_0 fixed by a strong prior.
  BorderedSystem rot(n, band, m);
  rot.add(0, 0, 1e9);
  for (int i = 1; i < total; ++i)
    rot.add(i, i, kPrior);
  for (const auto& e : edges) {
    const double w = e.weight;
    rot.add(e.to, e.to, w);
    rot.add(e.from, e.from, w);
    rot.add(e.to, e.from, -w);
    rot.add_rhs(e.to, w * e.relative.rotation_deg);
    rot.add_rhs(e.from, -w * e.relative.rotation_deg);
  }
  std::vector<double> theta = rot.solve();
  theta[0] = 0.0;
  // Shifts: d_to − R(θ_to − θ_from) d_from = e (unknowns interleaved x, y per node).
  BorderedSystem shift(2 * n, 2 * band + 1, 2 * m);
  shift.add(0, 0, 1e9);
  shift.add(1, 1, 1e9);
  for (int i = 2; i < 2 * total; ++i)
    shift.add(i, i, kPrior);
  for (const auto& e : edges) {
    const double a = (theta[std::size_t(e.to)] - theta[std::size_t(e.from)]) * kPi / 180.0;
    const double co = std::cos(a), si = std::sin(a);
    const double w = e.weight;
    // Row x: +1·x_to − co·x_from + si·y_from = ex;  row y: +1·y_to − si·x_from − co·y_from = ey.
    const double rows[2][3] = {{1.0, -co, si}, {1.0, -si, -co}};
    const double rhs[2] = {e.relative.dx_px, e.relative.dy_px};
    for (int r = 0; r < 2; ++r) {
      const int idx[3] = {2 * e.to + r, 2 * e.from, 2 * e.from + 1};
      for (int p = 0; p < 3; ++p) {
        for (int q = 0; q <= p; ++q) {
          const double v = w * rows[r][p] * rows[r][q];
          if (idx[p] == idx[q] && p != q) {
            shift.add(idx[p], idx[q], 2.0 * v);
          } else {
            shift.add(idx[p], idx[q], v);
          }
        }
        shift.add_rhs(idx[p], w * rows[r][p] * rhs[r]);
      }
    }
  }
  std::vector<double> d = shift.solve();
  for (int i = 1; i < total; ++i) {
    if (!reached[std::size_t(i)]) continue;
    out[std::size_t(i)] = {theta[std::size_t(i)], d[2 * std::size_t(i)], d[2 * std::size_t(i) + 1]};
  }
  return out;
}

namespace {

// Rigid least-squares fit p ≈ M(q) of matched points (at least two).
cv::Matx23d fit_rigid(const std::vector<cv::Point2d>& q, const std::vector<cv::Point2d>& p) {
  cv::Point2d qm(0, 0), pm(0, 0);
  for (std::size_t i = 0; i < q.size(); ++i)
    qm += q[i], pm += p[i];
  qm *= 1.0 / double(q.size());
  pm *= 1.0 / double(p.size());
  double sc = 0, ss = 0;
  for (std::size_t i = 0; i < q.size(); ++i) {
    const cv::Point2d a = q[i] - qm, b = p[i] - pm;
    sc += a.x * b.x + a.y * b.y;
    ss += a.x * b.y - a.y * b.x;
  }
  const double angle = std::atan2(ss, sc), co = std::cos(angle), si = std::sin(angle);
  return {co, -si, pm.x - (co * qm.x - si * qm.y), si, co, pm.y - (si * qm.x + co * qm.y)};
}

cv::Point2d apply(const cv::Matx23d& m, const cv::Point2d& p) {
  return {m(0, 0) * p.x + m(0, 1) * p.y + m(0, 2), m(1, 0) * p.x + m(1, 1) * p.y + m(1, 2)};
}

// Fiducial group edges (see register.h): `t` is the pair-edge-only solution. Returns the edges
// (free nodes numbered from n) and the number of groups.
constexpr double kTrackPx = 4.0;             // a fiducial continues a track within this distance
constexpr int kMinTrackLength = 3;           // tracks seen on fewer slices are ignored
constexpr double kFiducialWeight = 25.0;     // weight of a fiducial edge (a pair edge has 1)
constexpr double kFiducialResidualPx = 1.0;  // largest misfit of one fiducial in a group fit
constexpr double kFiducialAgreePx = 10.0;    // a fit further than this from the chain is dropped

// The fiducials of every usable slice followed on the output grid slice by slice (through the
// pair-edge-only solution `t`): per slice, the (track, fiducial position) pairs it sees; per
// track, on how many slices it was seen.
struct FiducialTracks {
  std::vector<std::vector<std::pair<int, cv::Point2d>>> seen;  // [slice] → (track, p)
  std::vector<int> length;                                     // [track] → slices seen on
  // Where slice k sees `track` (input pixels); (0, 0) when it does not.
  cv::Point2d point_of(int k, int track) const {
    for (const auto& s : seen[std::size_t(k)])
      if (s.first == track) return s.second;
    return cv::Point2d();
  }
};

FiducialTracks follow_tracks(const std::vector<SlicePairs>& pairs, const std::vector<Rigid>& t,
                             cv::Point2d c) {
  const int n = int(pairs.size());
  std::vector<cv::Point2d> last;  // [track] → its latest position on the output grid
  FiducialTracks tracks;
  tracks.seen.resize(static_cast<std::size_t>(n));
  for (int k = 0; k < n; ++k) {
    if (pairs[k].black || pairs[k].duplicate_of) continue;
    const cv::Matx23d to_output = invert_affine(rigid_matrix(t[std::size_t(k)], c));
    std::vector<bool> taken(last.size(), false);
    for (const auto& p : pairs[std::size_t(k)].fiducials) {
      const cv::Point2d q = apply(to_output, p);
      int best = -1;
      double best_d = kTrackPx;
      for (std::size_t i = 0; i < last.size(); ++i) {
        const double d = std::hypot(last[i].x - q.x, last[i].y - q.y);
        if (!taken[i] && d < best_d) best = int(i), best_d = d;
      }
      if (best < 0) {
        best = int(last.size());
        last.push_back(q);
        tracks.length.push_back(0);
        taken.push_back(false);
      }
      taken[std::size_t(best)] = true;
      last[std::size_t(best)] = q;
      ++tracks.length[std::size_t(best)];
      tracks.seen[std::size_t(k)].push_back({best, p});
    }
  }
  return tracks;
}

// One group's fiducial edges (from free node `node`): slices `slices` that all see the long
// tracks `key`. Each slice's fiducials are fitted rigidly to the group frame (the mean
// output-grid position of each track over the group); a slice whose fit leaves a residual or
// disagrees with the pair chain gets no edge.
std::vector<PairEdge> group_edges(const FiducialTracks& tracks, const std::vector<int>& key,
                                  const std::vector<int>& slices, const std::vector<Rigid>& t,
                                  cv::Size size, int node) {
  const cv::Point2d c = image_centre(size);
  std::vector<cv::Point2d> frame(key.size(), cv::Point2d(0, 0));
  for (int k : slices) {
    const cv::Matx23d to_output = invert_affine(rigid_matrix(t[std::size_t(k)], c));
    for (std::size_t i = 0; i < key.size(); ++i)
      frame[i] += apply(to_output, tracks.point_of(k, key[i]));
  }
  for (auto& f : frame)
    f *= 1.0 / double(slices.size());
  std::vector<PairEdge> group;
  for (int k : slices) {
    std::vector<cv::Point2d> observed;
    for (int track : key)
      observed.push_back(tracks.point_of(k, track));
    const cv::Matx23d fit_m = fit_rigid(frame, observed);
    // Fiducials are rigid: one that moved against the others (debris, a mismatch) shows as
    // a residual of the fit; such a slice gets no fiducial edge.
    double residual = 0.0;
    for (std::size_t i = 0; i < frame.size(); ++i) {
      const cv::Point2d d = apply(fit_m, frame[i]) - observed[i];
      residual = std::max(residual, std::hypot(d.x, d.y));
    }
    if (residual > kFiducialResidualPx) continue;
    const Rigid fit = rigid_from_matrix(fit_m, c);
    // Agreement with the pair chain (the group frame is close to the output grid).
    const cv::Matx23d diff =
        compose_affine(rigid_matrix(fit, c), invert_affine(rigid_matrix(t[std::size_t(k)], c)));
    if (rigid_motion_px(rigid_from_matrix(diff, c), size) > kFiducialAgreePx) continue;
    group.push_back({node, k, fit, kFiducialWeight});
  }
  return group;
}

std::vector<PairEdge> fiducial_edges(const std::vector<SlicePairs>& pairs,
                                     const std::vector<Rigid>& t, cv::Size size, int* groups) {
  const int n = int(pairs.size());
  const FiducialTracks tracks = follow_tracks(pairs, t, image_centre(size));
  // Groups: slices seeing the same set (>= 2) of long tracks.
  std::map<std::vector<int>, std::vector<int>> members;
  for (int k = 0; k < n; ++k) {
    std::vector<int> key;
    for (const auto& s : tracks.seen[std::size_t(k)])
      if (tracks.length[std::size_t(s.first)] >= kMinTrackLength) key.push_back(s.first);
    std::sort(key.begin(), key.end());
    if (key.size() >= 2) members[key].push_back(k);
  }
  std::vector<PairEdge> edges;
  int g = 0;
  for (const auto& [key, slices] : members) {
    if (int(slices.size()) < kMinTrackLength) continue;
    const std::vector<PairEdge> group = group_edges(tracks, key, slices, t, size, n + g);
    if (group.size() < 2) continue;
    edges.insert(edges.end(), group.begin(), group.end());
    ++g;
  }
  if (groups) *groups = g;
  return edges;
}

}  // namespace

std::vector<SliceTransform> chain_transforms(const std::vector<SlicePairs>& pairs, cv::Size size,
                                             double jump_px, int* fiducial_groups) {
  const int n = int(pairs.size());
  std::vector<PairEdge> edges;
  for (int k = 0; k < n; ++k) {
    if (pairs[k].index != k)
      throw Error(cat("chain_transforms: pair record ", k, " has index ", pairs[k].index));
    for (const auto& e : pairs[k].edges)
      edges.push_back(e);
  }
  std::vector<Rigid> t = solve_chain(n, edges);
  int groups = 0;
  const std::vector<PairEdge> fid = fiducial_edges(pairs, t, size, &groups);
  if (fiducial_groups) *fiducial_groups = groups;
  if (groups > 0) {
    edges.insert(edges.end(), fid.begin(), fid.end());
    t = solve_chain(n, edges, groups);
    t.resize(std::size_t(n));
  }
  std::vector<SliceTransform> out(static_cast<std::size_t>(n));
  auto usable = [&](int k) { return !pairs[k].black && !pairs[k].duplicate_of; };
  for (int k = 0; k < n; ++k) {
    SliceTransform& s = out[std::size_t(k)];
    s.index = k;
    s.black = pairs[k].black;
    s.duplicate_of = pairs[k].duplicate_of;
    s.quality = k == 0 ? 1.0 : pairs[k].quality;
    s.rigid = t[k];
  }
  // Black slices: interpolate between the nearest usable neighbours.
  for (int k = 0; k < n; ++k) {
    if (!pairs[k].black) continue;
    int a = k - 1, b = k + 1;
    while (a >= 0 && !usable(a))
      --a;
    while (b < n && !usable(b))
      ++b;
    Rigid ra = a >= 0 ? t[a] : (b < n ? t[b] : Rigid{});
    Rigid rb = b < n ? t[b] : ra;
    const double w = (a >= 0 && b < n) ? double(k - a) / double(b - a) : 0.0;
    SliceTransform& s = out[std::size_t(k)];
    s.rigid.rotation_deg = ra.rotation_deg + w * (rb.rotation_deg - ra.rotation_deg);
    s.rigid.dx_px = ra.dx_px + w * (rb.dx_px - ra.dx_px);
    s.rigid.dy_px = ra.dy_px + w * (rb.dy_px - ra.dy_px);
    s.quality = 0.0;
  }
  // Duplicates: the original's transform.
  for (int k = 0; k < n; ++k) {
    if (!pairs[k].duplicate_of) continue;
    const SliceTransform& o = out[std::size_t(*pairs[k].duplicate_of)];
    SliceTransform& s = out[std::size_t(k)];
    s.rigid = o.rigid;
    s.quality = o.quality;
  }
  // Jumps: motion from the previous usable slice to k.
  int prev = -1;
  for (int k = 0; k < n; ++k) {
    if (!usable(k)) continue;
    if (prev >= 0) {
      const cv::Point2d c = image_centre(size);
      cv::Matx23d tk = rigid_matrix(out[k].rigid, c);
      cv::Matx23d tp = rigid_matrix(out[prev].rigid, c);
      Rigid rel = rigid_from_matrix(compose_affine(tk, invert_affine(tp)), c);
      out[k].jump = rigid_motion_px(rel, size) > jump_px;
    }
    prev = k;
  }
  return out;
}

namespace {

// Nominal noise of the measurements (1σ), output pixels.
constexpr double kPairSigmaPx = 0.05;      // a pair estimate's random error
constexpr double kFirstOrderShare = 0.04;  // w_1 / w_a (nominal): first-order pair terms
constexpr double kFiducialSigmaPx = 0.05;  // a fiducial group fit (tubes: σ ≈ 0.05 px)
constexpr double kOutlierSigmas = 3.0;     // Cauchy scale of the robust reweighting
constexpr int kRobustPasses = 3;
constexpr double kFixedWeight = 1e8;         // a person's fixed transform
constexpr double kTinyBodyFraction = 0.005;  // body below 0.5 % of the frame: no pair edge
constexpr double kSmoothSigmaPx = 0.5;       // smoothness prior: second difference of the shift
constexpr double kSmoothSigmaDeg = 0.05;     // and of the rotation, per slice²
// Random-walk prior: the first difference of T is ~0 within these per slice (√gap across a
// gap), cut at jumps. The drift of a cryosection stack is a slow random walk (~0.3 px and
// ~0.05° per slice); these are twice that, so they only decide where anchors are noisy (a
// small body's rotation) or missing, and never integrate a measurement.
constexpr double kWalkSigmaPx = 0.6;
constexpr double kWalkSigmaDeg = 0.1;
// A measured step beyond this many walk σ at the body cuts the prior (find_cuts).
constexpr double kCutWalkSigmas = 4.0;

// Sparse weighted least squares over a banded block (slices) and a dense border (free frames).
class LeastSquares {
 public:
  LeastSquares(int n, int band, int m) : sys_(n, band, m), total_(n + m) {
    for (int i = 0; i < total_; ++i)
      sys_.add(i, i, 1e-9);
  }
  // Row Σ c_i x_{idx_i} ≈ rhs with weight w (indices distinct).
  void row(std::initializer_list<std::pair<int, double>> terms, double rhs, double w) {
    if (!(w > 0.0)) return;
    for (auto a = terms.begin(); a != terms.end(); ++a) {
      for (auto b = terms.begin(); b != a; ++b)
        sys_.add(a->first, b->first, w * a->second * b->second);
      sys_.add(a->first, a->first, w * a->second * a->second);
      sys_.add_rhs(a->first, w * a->second * rhs);
    }
  }
  std::vector<double> solve() { return sys_.solve(); }

 private:
  BorderedSystem sys_;
  int total_;
};

double cauchy(double residual, double sigma) {
  const double r = residual / (kOutlierSigmas * sigma);
  return 1.0 / (1.0 + r * r);
}

// Relative transform A ⊖ B = A ∘ B⁻¹ (B's observed grid to A's), about centre c.
Rigid relative(const Rigid& a, const Rigid& b, cv::Point2d c) {
  return rigid_from_matrix(compose_affine(rigid_matrix(a, c), invert_affine(rigid_matrix(b, c))),
                           c);
}

// Anchor mode "none" or "fiducials": the slice-0-referenced chain (plus fiducial groups); a
// person's fixed transform is an edge from the reference (T_0 = identity) with an overwhelming
// weight. `over[k]`: slice k's override, if any.
StackSolve solve_without_ct(const std::vector<SlicePairs>& pairs, cv::Size size,
                            const StackSolveOptions& options,
                            const std::vector<const SliceOverride*>& over) {
  const int n = int(pairs.size());
  StackSolve result;
  auto usable = [&](int k) {
    return !pairs[std::size_t(k)].black && !pairs[std::size_t(k)].duplicate_of;
  };
  std::vector<SlicePairs> p = pairs;
  for (const auto& o : options.overrides)
    if (o.transform && o.index > 0 && usable(o.index))
      p[std::size_t(o.index)].edges.push_back({0, o.index, *o.transform, kFixedWeight});
  int groups = 0;
  if (options.anchor == "none") {
    for (auto& r : p)
      r.fiducials.clear();
  }
  result.slices = chain_transforms(p, size, options.jump_px, &groups);
  result.fiducial_groups = groups;
  result.frame = groups > 0 ? "fiducials" : "slice0";
  if (options.anchor == "none" && n > 2) {
    // Regularised: without an absolute reference the drift's lowest frequencies are not
    // observable, and integrating the pairs would turn the anatomy's apparent motion into
    // drift without bound. A zero-phase exponential low-pass (window 100 slices) of the
    // chained transforms is subtracted: what the pairs measure locally stays, a steady bias
    // (a ramp) is removed in the interior and nothing integrates beyond ~100 slices.
    constexpr double kWindow = 100.0;
    const double a = 1.0 / kWindow;
    std::vector<Rigid> t(static_cast<std::size_t>(n));
    for (int k = 0; k < n; ++k)
      t[std::size_t(k)] = result.slices[std::size_t(k)].rigid;
    // Exponential low-pass, forward and backward (zero phase), subtracted from k >= 1.
    std::vector<Rigid> lp = t;
    for (int pass = 0; pass < 2; ++pass) {
      const int start = pass == 0 ? 1 : n - 2, step = pass == 0 ? 1 : -1;
      for (int k = start; k >= 0 && k < n; k += step) {
        const Rigid& prev = lp[std::size_t(k - step)];
        Rigid& cur = lp[std::size_t(k)];
        cur = {prev.rotation_deg + a * (cur.rotation_deg - prev.rotation_deg),
               prev.dx_px + a * (cur.dx_px - prev.dx_px),
               prev.dy_px + a * (cur.dy_px - prev.dy_px)};
      }
    }
    for (int k = 1; k < n; ++k) {
      if (over[std::size_t(k)] && over[std::size_t(k)]->transform) continue;
      Rigid& s = result.slices[std::size_t(k)].rigid;
      s.rotation_deg -= lp[std::size_t(k)].rotation_deg - lp[0].rotation_deg;
      s.dx_px -= lp[std::size_t(k)].dx_px - lp[0].dx_px;
      s.dy_px -= lp[std::size_t(k)].dy_px - lp[0].dy_px;
    }
  }
  for (const auto& o : options.overrides) {
    if (o.transform) {
      result.slices[std::size_t(o.index)].rigid = *o.transform;
    }
    if (o.jump) result.slices[std::size_t(o.index)].jump = true;
  }
  return result;
}

// Anchor mode "ct" (the terms at the top of solve.h). The unknowns are the usable slices
// ("nodes": neither black nor a duplicate); the solve is built step by step: nodes, anchors,
// the pair edges kept, the cuts, then two rounds (the second with fiducial groups, where tubes
// are seen) of rotations then shifts, each reweighted kRobustPasses times; write_slices gives
// every slice its transform.
class CtStackSolver {
 public:
  CtStackSolver(const std::vector<SlicePairs>& pairs, cv::Size size,
                const StackSolveOptions& options, const std::vector<const SliceOverride*>& over,
                StackSolve& result)
      : pairs_(pairs),
        size_(size),
        options_(options),
        over_(over),
        result_(result),
        n_(int(pairs.size())),
        c_(image_centre(size)),
        r0_(0.25 * 0.5 * (size.width + size.height)) {
    make_nodes();
    gather_anchors();
    reject_pairs();
    find_cuts();
  }

  void solve();
  void write_slices();

 private:
  struct Anchor {
    Rigid t;
    double w_shift = 0, w_rot = 0, sigma = 1;
    bool fixed = false;
  };
  struct FiducialTerm {
    int group, node;
    Rigid fit;
  };

  bool usable(int k) const {
    return !pairs_[std::size_t(k)].black && !pairs_[std::size_t(k)].duplicate_of;
  }
  const std::optional<AnchorEstimate>& record(int i) const {
    return pairs_[std::size_t(node_slice_[std::size_t(i)])].anchor;
  }
  double gap(int i) const {
    return double(node_slice_[std::size_t(i)] - node_slice_[std::size_t(i - 1)]);
  }
  double pair_sigma(int i) const;
  double pair_lever_at(int i) const;
  double edge_share(int i) const;
  double edge_lever_share(int i) const;
  bool tiny_body(int i) const;
  bool confident_anchor(int i) const;
  bool curvature_ok(int i) const {  // terms around node i use edges into i and i+1
    return i >= 1 && i + 1 < m_ && primary_[std::size_t(i)] && primary_[std::size_t(i + 1)];
  }
  bool smooth_ok(int i) const {
    return i >= 1 && i + 1 < m_ && !cut_[std::size_t(i)] && !cut_[std::size_t(i + 1)] &&
           i - 1 >= first_anchored_ && i + 1 <= last_anchored_;
  }

  void make_nodes();
  void gather_anchors();
  void reject_pairs();
  void find_cuts();
  std::vector<double> solve_rotations() const;
  std::vector<double> solve_shifts(const std::vector<double>& theta) const;
  void reweight();

  const std::vector<SlicePairs>& pairs_;
  const cv::Size size_;
  const StackSolveOptions& options_;
  const std::vector<const SliceOverride*>& over_;
  StackSolve& result_;
  const int n_;
  const cv::Point2d c_;
  const double r0_;  // a "large" body radius, px: a quarter of the slice's mean edge

  std::vector<int> node_slice_;  // node → stack index
  std::vector<int> slice_node_;  // stack index → node (−1: not solved)
  int m_ = 0;
  std::vector<Rigid> solved_;
  // Primary pair edge into each node (from the previous node), unless cut or rejected.
  std::vector<std::optional<PairEdge>> primary_;
  std::vector<std::optional<Anchor>> anchor_;  // anchors and fixed transforms
  double nominal_wa_ = 0.0;  // 1/σ_a² of a confident anchor (for the first-order pair weight)
  std::vector<double> radius_;
  double pair_lever_ = 0, w1_shift_ = 0, w1_rot_ = 0;
  std::vector<bool> cut_;  // cut_[i]: between node i−1 and i
  int first_anchored_ = 0, last_anchored_ = -1;
  bool any_anchor_ = false;
  // Robust weights (Cauchy) of anchors and curvature terms, per component (rotation, shift),
  // and the noise scale factors of the four classes (reweight()).
  std::vector<double> ra_rot_, ra_shift_, rc_rot_, rc_shift_;
  double f_ar_ = 1.0, f_as_ = 1.0, f_cr_ = 1.0, f_cs_ = 1.0;
  std::vector<FiducialTerm> fid_;
  int groups_ = 0;
};

void CtStackSolver::make_nodes() {
  slice_node_.assign(static_cast<std::size_t>(n_), -1);
  for (int k = 0; k < n_; ++k)
    if (usable(k)) slice_node_[std::size_t(k)] = int(node_slice_.size()), node_slice_.push_back(k);
  m_ = int(node_slice_.size());
  solved_.resize(static_cast<std::size_t>(m_));
  primary_.resize(static_cast<std::size_t>(m_));
  for (int i = 1; i < m_; ++i) {
    const int k = node_slice_[std::size_t(i)];
    if (over_[std::size_t(k)] && over_[std::size_t(k)]->jump) continue;  // a person's cut
    for (const auto& e : pairs_[std::size_t(k)].edges)
      if (e.from == node_slice_[std::size_t(i - 1)]) {
        primary_[std::size_t(i)] = e;
        break;
      }
  }
}

void CtStackSolver::gather_anchors() {
  anchor_.resize(static_cast<std::size_t>(m_));
  for (int i = 0; i < m_; ++i) {
    const int k = node_slice_[std::size_t(i)];
    const SliceOverride* o = over_[std::size_t(k)];
    if (o && o->transform) {
      anchor_[std::size_t(i)] = Anchor{*o->transform, kFixedWeight, kFixedWeight, 1e-4, true};
      continue;
    }
    const auto& a = pairs_[std::size_t(k)].anchor;
    if (!a || !a->ok || a->confidence <= 0.0 || (o && o->exclude_anchor)) continue;
    const double sigma = std::max(a->sigma_px, 1e-3);
    const double lever = std::max(a->lever_px, 0.5) * kPi / 180.0;  // px per degree
    anchor_[std::size_t(i)] = Anchor{a->transform, a->confidence / (sigma * sigma),
                                     a->confidence * lever * lever / (sigma * sigma), sigma, false};
    nominal_wa_ = std::max(nominal_wa_, 1.0 / (sigma * sigma));
  }
  if (nominal_wa_ == 0.0) nominal_wa_ = 1.0;
  // Pair terms: σ_p for a body of radius ≥ R0 (a quarter of the mean edge); a smaller body
  // (the stack's ends) carries less information and often locks onto the gel: σ grows as
  // (R0 / r)², and the rotation's lever is the body's radius r (from the CT anchor's record;
  // R0 without one).
  pair_lever_ = r0_ * kPi / 180.0;
  radius_.assign(static_cast<std::size_t>(m_), r0_);
  for (int i = 0; i < m_; ++i) {
    const auto& a = record(i);
    if (a && a->radius_px > 0.0) radius_[std::size_t(i)] = std::max(5.0, a->radius_px);
  }
  w1_shift_ = kFirstOrderShare * nominal_wa_;
  w1_rot_ = w1_shift_ * pair_lever_ * pair_lever_;
  first_anchored_ = m_;
  for (int i = 0; i < m_; ++i)
    if (anchor_[std::size_t(i)]) first_anchored_ = std::min(first_anchored_, i), last_anchored_ = i;
  // With no anchor at all, the stack is still solved (pairs only) but unanchored: node 0 pinned.
  for (const auto& a : anchor_)
    any_anchor_ = any_anchor_ || bool(a);
}

double CtStackSolver::pair_sigma(int i) const {  // σ (px) of the curvature term around node i
  const double r =
      std::min({radius_[std::size_t(i - 1)], radius_[std::size_t(i)], radius_[std::size_t(i + 1)]});
  return kPairSigmaPx * std::max(1.0, (r0_ / r) * (r0_ / r));
}

double CtStackSolver::pair_lever_at(int i) const {
  return std::min({radius_[std::size_t(i - 1)], radius_[std::size_t(i)],
                   radius_[std::size_t(i + 1)], r0_}) *
         kPi / 180.0;
}

// The first-order term of the edge into node i, as the curvature terms: (σ_p / σ)² with σ grown as
// (R0 / r)² for the smaller body r of the two slices, and the rotation's lever (r, not R0) as a
// share of R0's, squared. A small body (the top of a head, a foot) says little about rotation:
// its pair estimates move with the anatomy by degrees while its anchor is right.
double CtStackSolver::edge_share(int i) const {
  const double r = std::min(radius_[std::size_t(i - 1)], radius_[std::size_t(i)]);
  const double grow = std::max(1.0, (r0_ / r) * (r0_ / r));
  return 1.0 / (grow * grow);
}

double CtStackSolver::edge_lever_share(int i) const {
  const double r = std::min({radius_[std::size_t(i - 1)], radius_[std::size_t(i)], r0_});
  return (r / r0_) * (r / r0_);
}

// A pair edge between slices of which one shows (almost) no body measures gel against gel:
// dropped (such slices follow their neighbours through the smoothness prior instead).
bool CtStackSolver::tiny_body(int i) const {
  const auto& a = record(i);
  return a && (a->body_fraction < kTinyBodyFraction || a->radius_px < 0.25 * r0_);
}

// A pair edge that claims a jump (motion > jump_px) is kept only where two confident anchors
// can confirm it (reject_pairs): at the ends of the stack a pair that lost track claims jumps
// that are not there.
bool CtStackSolver::confident_anchor(int i) const {
  const auto& a = anchor_[std::size_t(i)];
  if (!a) return false;
  if (a->fixed) return true;
  return record(i)->confidence >= 0.3;
}

void CtStackSolver::reject_pairs() {
  for (int i = 1; i < m_; ++i) {
    if (!primary_[std::size_t(i)]) continue;
    const bool unverified_jump =
        !(confident_anchor(i - 1) && confident_anchor(i)) &&
        rigid_motion_px(primary_[std::size_t(i)]->relative, size_) > options_.jump_px;
    if (tiny_body(i - 1) || tiny_body(i) || unverified_jump) {
      primary_[std::size_t(i)].reset();
      ++result_.pairs_rejected;
    }
  }
  // Gate: a pair edge that contradicts the two anchors it joins is dropped before the solve
  // (a pair on a small patch of body at the stack's end can lock onto the gel and report tens
  // of degrees). The disagreement is measured at the body (shift at the centre plus rotation
  // times the smaller radius of gyration) against 1 px + 3σ of the anchors' difference.
  for (int i = 1; i < m_; ++i) {
    if (!primary_[std::size_t(i)]) continue;
    const auto& a0 = anchor_[std::size_t(i - 1)];
    const auto& a1 = anchor_[std::size_t(i)];
    const auto& rec0 = record(i - 1);
    const auto& rec1 = record(i);
    if (!a0 || !a1) continue;
    const double conf =
        std::min(a0->fixed ? 1.0 : rec0->confidence, a1->fixed ? 1.0 : rec1->confidence);
    if (conf < 0.3) continue;
    const double radius = std::max(
        10.0, std::min(a0->fixed ? 1e3 : rec0->radius_px, a1->fixed ? 1e3 : rec1->radius_px));
    const Rigid measured = relative(a1->t, a0->t, c_);
    const Rigid& p = primary_[std::size_t(i)]->relative;
    const double disagree = std::hypot(p.dx_px - measured.dx_px, p.dy_px - measured.dy_px) +
                            std::abs(p.rotation_deg - measured.rotation_deg) * kPi / 180.0 * radius;
    const double gate = 1.0 + 3.0 * std::hypot(a0->sigma, a1->sigma) / std::sqrt(conf);
    if (disagree > gate) {
      primary_[std::size_t(i)].reset();
      ++result_.pairs_rejected;
    }
  }
}

// Smoothness prior (weak; what decides where neither anchors nor pairs do: the ends of the
// stack): the second difference of T is ~0 within σ_s, cut at a jump: one a person marked,
// or where the motion exceeds jump_px, judged by the two anchors when both are confident
// (a pair on a small patch of body can report a false jump) and by the pair otherwise.
void CtStackSolver::find_cuts() {
  cut_.assign(static_cast<std::size_t>(m_), false);
  for (int i = 1; i < m_; ++i) {
    const int k = node_slice_[std::size_t(i)];
    if (over_[std::size_t(k)] && over_[std::size_t(k)]->jump) {
      cut_[std::size_t(i)] = true;
      continue;
    }
    const auto& a0 = anchor_[std::size_t(i - 1)];
    const auto& a1 = anchor_[std::size_t(i)];
    const auto& rec0 = record(i - 1);
    const auto& rec1 = pairs_[std::size_t(k)].anchor;
    const bool confident = a0 && a1 && (a0->fixed || rec0->confidence >= 0.3) &&
                           (a1->fixed || rec1->confidence >= 0.3);
    if (confident) {
      // Judged at the body (shift at the centre + rotation × lever), where the anchors are
      // accurate, not at the frame's corners, where their rotation noise is magnified.
      const Rigid d = relative(a1->t, a0->t, c_);
      const double lever =
          std::min(a0->fixed ? r0_ : rec0->lever_px, a1->fixed ? r0_ : rec1->lever_px);
      auto at_body = [&](const Rigid& r) {
        return std::hypot(r.dx_px, r.dy_px) + std::abs(r.rotation_deg) * kPi / 180.0 * lever;
      };
      const double step = at_body(d);
      // A step under jump_px that the two anchors and the pair edge between them (which passed
      // reject_pairs' gate against the anchors) agree on, and that the walk prior cannot
      // produce (beyond kCutWalkSigmas of its step at the body), is measured, not drift: the
      // prior is cut there too, else it spreads a small block jump (3..6 px, a few degrees)
      // over its neighbours (docs/ARCHITECTURE.md, "Registration").
      const double walk_step =
          kCutWalkSigmas * std::hypot(kWalkSigmaPx, kWalkSigmaDeg * kPi / 180.0 * lever);
      cut_[std::size_t(i)] =
          step > options_.jump_px || (step > walk_step && primary_[std::size_t(i)] &&
                                      at_body(primary_[std::size_t(i)]->relative) > walk_step);
    } else if (primary_[std::size_t(i)]) {
      cut_[std::size_t(i)] =
          rigid_motion_px(primary_[std::size_t(i)]->relative, size_) > options_.jump_px;
    }
  }
  ra_rot_.assign(static_cast<std::size_t>(m_), 1.0);
  ra_shift_ = ra_rot_;
  rc_rot_ = ra_rot_;
  rc_shift_ = ra_rot_;
}

// The rotations θ of the nodes (then of the fiducial groups), the shifts held out.
std::vector<double> CtStackSolver::solve_rotations() const {
  const double ws_rot = 1.0 / (kSmoothSigmaDeg * kSmoothSigmaDeg);
  const double ww_rot = 1.0 / (kWalkSigmaDeg * kWalkSigmaDeg);
  const double wf_shift = 1.0 / (kFiducialSigmaPx * kFiducialSigmaPx);
  const double wf_rot = wf_shift * std::pow(2.0 * r0_ * kPi / 180.0, 2);
  LeastSquares rot(m_, 2, groups_);
  for (const auto& f : fid_)
    rot.row({{f.node, 1.0}, {m_ + f.group, -1.0}}, f.fit.rotation_deg, wf_rot);
  if (!any_anchor_ && m_ > 0) rot.row({{0, 1.0}}, 0.0, kFixedWeight);
  for (int i = 0; i < m_; ++i) {
    if (anchor_[std::size_t(i)])
      rot.row({{i, 1.0}}, anchor_[std::size_t(i)]->t.rotation_deg,
              anchor_[std::size_t(i)]->w_rot * ra_rot_[std::size_t(i)] / (f_ar_ * f_ar_));
    if (i >= 1 && primary_[std::size_t(i)]) {
      const PairEdge& e = *primary_[std::size_t(i)];
      rot.row({{i, 1.0}, {i - 1, -1.0}}, e.relative.rotation_deg,
              w1_rot_ * e.weight * edge_share(i) * edge_lever_share(i));
    }
    if (i >= 1 && !cut_[std::size_t(i)]) rot.row({{i, 1.0}, {i - 1, -1.0}}, 0.0, ww_rot / gap(i));
    if (smooth_ok(i))
      rot.row(
          {{i + 1, 1.0 / gap(i + 1)}, {i, -1.0 / gap(i + 1) - 1.0 / gap(i)}, {i - 1, 1.0 / gap(i)}},
          0.0, ws_rot);
    if (curvature_ok(i)) {
      const PairEdge& e1 = *primary_[std::size_t(i)];
      const PairEdge& e2 = *primary_[std::size_t(i + 1)];
      const double g1 = gap(i), g2 = gap(i + 1);
      const double sl = pair_sigma(i) / pair_lever_at(i);  // degrees
      const double w =
          std::min(e1.weight, e2.weight) * rc_rot_[std::size_t(i)] / (sl * sl * f_cr_ * f_cr_);
      rot.row({{i + 1, 1.0 / g2}, {i, -1.0 / g2 - 1.0 / g1}, {i - 1, 1.0 / g1}},
              e2.relative.rotation_deg / g2 - e1.relative.rotation_deg / g1, w);
    }
  }
  return rot.solve();
}

// The shifts d (x, y interleaved; then the fiducial groups'), the rotations `theta` fixed.
std::vector<double> CtStackSolver::solve_shifts(const std::vector<double>& theta) const {
  const double ws_shift = 1.0 / (kSmoothSigmaPx * kSmoothSigmaPx);
  const double ww_shift = 1.0 / (kWalkSigmaPx * kWalkSigmaPx);
  const double wf_shift = 1.0 / (kFiducialSigmaPx * kFiducialSigmaPx);
  LeastSquares sh(2 * m_, 5, 2 * groups_);
  if (!any_anchor_ && m_ > 0) {
    sh.row({{0, 1.0}}, 0.0, kFixedWeight);
    sh.row({{1, 1.0}}, 0.0, kFixedWeight);
  }
  auto rmat = [&](int i, int j) {  // R(θ_i − θ_j)
    const double a = (theta[std::size_t(i)] - theta[std::size_t(j)]) * kPi / 180.0;
    return cv::Matx22d(std::cos(a), -std::sin(a), std::sin(a), std::cos(a));
  };
  for (const auto& f : fid_) {
    // d_k − R(θ_k − θ_g) d_g = e
    const cv::Matx22d r = rmat(f.node, m_ + f.group);
    const int g = 2 * m_ + 2 * f.group;
    sh.row({{2 * f.node, 1.0}, {g, -r(0, 0)}, {g + 1, -r(0, 1)}}, f.fit.dx_px, wf_shift);
    sh.row({{2 * f.node + 1, 1.0}, {g, -r(1, 0)}, {g + 1, -r(1, 1)}}, f.fit.dy_px, wf_shift);
  }
  for (int i = 0; i < m_; ++i) {
    if (anchor_[std::size_t(i)]) {
      const double w =
          anchor_[std::size_t(i)]->w_shift * ra_shift_[std::size_t(i)] / (f_as_ * f_as_);
      sh.row({{2 * i, 1.0}}, anchor_[std::size_t(i)]->t.dx_px, w);
      sh.row({{2 * i + 1, 1.0}}, anchor_[std::size_t(i)]->t.dy_px, w);
    }
    if (i >= 1 && primary_[std::size_t(i)]) {
      // d_i − R(θ_i − θ_{i−1}) d_{i−1} = e
      const PairEdge& e = *primary_[std::size_t(i)];
      const cv::Matx22d r = rmat(i, i - 1);
      const double w = w1_shift_ * e.weight * edge_share(i);
      sh.row({{2 * i, 1.0}, {2 * (i - 1), -r(0, 0)}, {2 * (i - 1) + 1, -r(0, 1)}}, e.relative.dx_px,
             w);
      sh.row({{2 * i + 1, 1.0}, {2 * (i - 1), -r(1, 0)}, {2 * (i - 1) + 1, -r(1, 1)}},
             e.relative.dy_px, w);
    }
    if (i >= 1 && !cut_[std::size_t(i)]) {
      // d_i − R(θ_i − θ_{i−1}) d_{i−1} = 0: no motion between neighbours (random walk).
      const cv::Matx22d r = rmat(i, i - 1);
      const double w = ww_shift / gap(i);
      sh.row({{2 * i, 1.0}, {2 * (i - 1), -r(0, 0)}, {2 * (i - 1) + 1, -r(0, 1)}}, 0.0, w);
      sh.row({{2 * i + 1, 1.0}, {2 * (i - 1), -r(1, 0)}, {2 * (i - 1) + 1, -r(1, 1)}}, 0.0, w);
    }
    if (smooth_ok(i)) {
      const double g1 = gap(i), g2 = gap(i + 1);
      for (int row = 0; row < 2; ++row)
        sh.row({{2 * (i + 1) + row, 1.0 / g2},
                {2 * i + row, -1.0 / g2 - 1.0 / g1},
                {2 * (i - 1) + row, 1.0 / g1}},
               0.0, ws_shift);
    }
    if (curvature_ok(i)) {
      // (d_{i+1} − R₂ d_i − e₂)/g₂ − (d_i − R₁ d_{i−1} − e₁)/g₁ = 0
      const PairEdge& e1 = *primary_[std::size_t(i)];
      const PairEdge& e2 = *primary_[std::size_t(i + 1)];
      const double g1 = gap(i), g2 = gap(i + 1);
      const cv::Matx22d r2 = rmat(i + 1, i), r1 = rmat(i, i - 1);
      const double w = std::min(e1.weight, e2.weight) * rc_shift_[std::size_t(i)] /
                       (pair_sigma(i) * pair_sigma(i) * f_cs_ * f_cs_);
      for (int row = 0; row < 2; ++row) {
        // Coefficients on d_{i+1}[row], d_i[0..1], d_{i−1}[0..1].
        const double di0 = -r2(row, 0) / g2 - (row == 0 ? 1.0 : 0.0) / g1;
        const double di1 = -r2(row, 1) / g2 - (row == 1 ? 1.0 : 0.0) / g1;
        const double rhs = (row == 0 ? e2.relative.dx_px : e2.relative.dy_px) / g2 -
                           (row == 0 ? e1.relative.dx_px : e1.relative.dy_px) / g1;
        sh.row({{2 * (i + 1) + row, 1.0 / g2},
                {2 * i, di0},
                {2 * i + 1, di1},
                {2 * (i - 1), r1(row, 0) / g1},
                {2 * (i - 1) + 1, r1(row, 1) / g1}},
               rhs, w);
      }
    }
  }
  return sh.solve();
}

// Noise levels from the data, then robust weights. Each class of measurement (anchor rotation,
// anchor shift, pair-curvature rotation, pair-curvature shift) gets a scale factor f = 1.4826 ·
// median of its normalised residuals (at least 1): where the anatomy makes pair estimates noisy
// (or the anchors are poor), that class weighs less, on this stack. Then each term is
// down-weighted by Cauchy(residual / (3 f σ)).
void CtStackSolver::reweight() {
  std::vector<double> z_ar, z_as, z_cr, z_cs;
  std::vector<double> zi_ar(static_cast<std::size_t>(m_), 0.0), zi_as(zi_ar), zi_cr(zi_ar),
      zi_cs(zi_ar);
  for (int i = 0; i < m_; ++i) {
    if (anchor_[std::size_t(i)] && !anchor_[std::size_t(i)]->fixed) {
      const Anchor& a = *anchor_[std::size_t(i)];
      const double lever = std::sqrt(a.w_rot / std::max(a.w_shift, 1e-12));  // px per degree
      const double q = std::sqrt(std::max(a.w_shift, 1e-12)) * a.sigma;      // √confidence
      const Rigid& t = solved_[std::size_t(i)];
      zi_ar[std::size_t(i)] = std::abs(t.rotation_deg - a.t.rotation_deg) * lever * q / a.sigma;
      zi_as[std::size_t(i)] =
          std::hypot(t.dx_px - a.t.dx_px, t.dy_px - a.t.dy_px) * q / (a.sigma * std::sqrt(2.0));
      z_ar.push_back(zi_ar[std::size_t(i)]);
      z_as.push_back(zi_as[std::size_t(i)]);
    }
    if (curvature_ok(i)) {
      const Rigid r1 = relative(solved_[std::size_t(i)], solved_[std::size_t(i - 1)], c_);
      const Rigid r2 = relative(solved_[std::size_t(i + 1)], solved_[std::size_t(i)], c_);
      const PairEdge& e1 = *primary_[std::size_t(i)];
      const PairEdge& e2 = *primary_[std::size_t(i + 1)];
      const double g1 = gap(i), g2 = gap(i + 1);
      const double cr = (r2.rotation_deg - e2.relative.rotation_deg) / g2 -
                        (r1.rotation_deg - e1.relative.rotation_deg) / g1;
      const double cx = (r2.dx_px - e2.relative.dx_px) / g2 - (r1.dx_px - e1.relative.dx_px) / g1;
      const double cy = (r2.dy_px - e2.relative.dy_px) / g2 - (r1.dy_px - e1.relative.dy_px) / g1;
      zi_cr[std::size_t(i)] = std::abs(cr) * pair_lever_at(i) / pair_sigma(i);
      zi_cs[std::size_t(i)] = std::hypot(cx, cy) / (pair_sigma(i) * std::sqrt(2.0));
      z_cr.push_back(zi_cr[std::size_t(i)]);
      z_cs.push_back(zi_cs[std::size_t(i)]);
    }
  }
  auto scale = [](std::vector<double> z) {
    if (z.size() < 5) return 1.0;
    std::nth_element(z.begin(), z.begin() + z.size() / 2, z.end());
    return std::max(1.0, 1.4826 * z[z.size() / 2]);
  };
  f_ar_ = scale(z_ar), f_as_ = scale(z_as), f_cr_ = scale(z_cr), f_cs_ = scale(z_cs);
  for (int i = 0; i < m_; ++i) {
    ra_rot_[std::size_t(i)] = cauchy(zi_ar[std::size_t(i)], f_ar_);
    ra_shift_[std::size_t(i)] = cauchy(zi_as[std::size_t(i)], f_as_);
    rc_rot_[std::size_t(i)] = cauchy(zi_cr[std::size_t(i)], f_cr_);
    rc_shift_[std::size_t(i)] = cauchy(zi_cs[std::size_t(i)], f_cs_);
  }
}

// Two rounds: the second, where fiducial groups are found on the grid of the first, adds the
// groups' frames as free unknowns (the border of the banded systems) tied to each slice of the
// group. Each round solves rotations then shifts, reweighting kRobustPasses times.
void CtStackSolver::solve() {
  for (int round = 0; round < 2 && m_ > 0; ++round) {
    if (round == 1) {
      std::vector<Rigid> t_all(static_cast<std::size_t>(n_));
      for (int i = 0; i < m_; ++i)
        t_all[std::size_t(node_slice_[std::size_t(i)])] = solved_[std::size_t(i)];
      for (const PairEdge& e : fiducial_edges(pairs_, t_all, size_, &groups_))
        fid_.push_back({e.from - n_, slice_node_[std::size_t(e.to)], e.relative});
      result_.fiducial_groups = groups_;
      if (groups_ == 0) break;
    }
    for (int pass = 0; pass <= kRobustPasses; ++pass) {
      const std::vector<double> theta = solve_rotations();
      const std::vector<double> d = solve_shifts(theta);
      for (int i = 0; i < m_; ++i)
        solved_[std::size_t(i)] = {theta[std::size_t(i)], d[2 * std::size_t(i)],
                                   d[2 * std::size_t(i) + 1]};
      if (pass == kRobustPasses) break;
      reweight();
    }
  }
}

// Every slice's transform: the solved nodes; black slices interpolated between their usable
// neighbours, duplicates copied, a person's fixed transforms; per slice the anchor's confidence
// and residual; jumps where the solved motion exceeds jump_px (or a person marked one).
void CtStackSolver::write_slices() {
  result_.slices.resize(std::size_t(n_));
  for (int k = 0; k < n_; ++k) {
    SliceTransform& s = result_.slices[std::size_t(k)];
    s.index = k;
    s.black = pairs_[std::size_t(k)].black;
    s.duplicate_of = pairs_[std::size_t(k)].duplicate_of;
    s.quality = pairs_[std::size_t(k)].quality;
    const int i = slice_node_[std::size_t(k)];
    if (i >= 0) s.rigid = solved_[std::size_t(i)];
  }
  for (int k = 0; k < n_; ++k) {
    if (!pairs_[std::size_t(k)].black) continue;
    int a = k - 1, b = k + 1;
    while (a >= 0 && !usable(a))
      --a;
    while (b < n_ && !usable(b))
      ++b;
    const SliceTransform* ta = a >= 0 ? &result_.slices[std::size_t(a)] : nullptr;
    const SliceTransform* tb = b < n_ ? &result_.slices[std::size_t(b)] : nullptr;
    if (!ta) ta = tb;
    if (!tb) tb = ta;
    SliceTransform& s = result_.slices[std::size_t(k)];
    s.quality = 0.0;
    if (!ta) continue;
    const double w = (a >= 0 && b < n_) ? double(k - a) / double(b - a) : 0.0;
    s.rigid.rotation_deg =
        ta->rigid.rotation_deg + w * (tb->rigid.rotation_deg - ta->rigid.rotation_deg);
    s.rigid.dx_px = ta->rigid.dx_px + w * (tb->rigid.dx_px - ta->rigid.dx_px);
    s.rigid.dy_px = ta->rigid.dy_px + w * (tb->rigid.dy_px - ta->rigid.dy_px);
  }
  for (int k = 0; k < n_; ++k) {
    if (!pairs_[std::size_t(k)].duplicate_of) continue;
    const SliceTransform& o = result_.slices[std::size_t(*pairs_[std::size_t(k)].duplicate_of)];
    result_.slices[std::size_t(k)].rigid = o.rigid;
  }
  for (const auto& o : options_.overrides) {
    if (!o.transform) continue;
    result_.slices[std::size_t(o.index)].rigid = *o.transform;
  }
  for (int k = 0; k < n_; ++k) {
    SliceTransform& s = result_.slices[std::size_t(k)];
    const auto& a = pairs_[std::size_t(k)].anchor;
    if (!a) continue;
    s.extra["anchor_confidence"] = a->ok ? a->confidence : 0.0;
    if (a->ok)
      s.extra["anchor_residual_px"] = rigid_motion_px(relative(a->transform, s.rigid, c_), size_);
    const int i = slice_node_[std::size_t(k)];
    if (i >= 0 && anchor_[std::size_t(i)] && !anchor_[std::size_t(i)]->fixed) {
      ++result_.anchors_used;
      if (ra_shift_[std::size_t(i)] < 0.5 || ra_rot_[std::size_t(i)] < 0.5)
        ++result_.anchors_downweighted;
    }
  }
  int prev = -1;
  for (int k = 0; k < n_; ++k) {
    if (!usable(k)) continue;
    SliceTransform& s = result_.slices[std::size_t(k)];
    if (prev >= 0) {
      const SliceTransform& p = result_.slices[std::size_t(prev)];
      s.jump = rigid_motion_px(relative(s.rigid, p.rigid, c_), size_) > options_.jump_px;
    }
    if (over_[std::size_t(k)] && over_[std::size_t(k)]->jump) s.jump = true;
    prev = k;
  }
}

}  // namespace

StackSolve solve_stack(const std::vector<SlicePairs>& pairs, cv::Size size,
                       const StackSolveOptions& options) {
  const int n = int(pairs.size());
  for (int k = 0; k < n; ++k)
    if (pairs[std::size_t(k)].index != k)
      throw Error(cat("solve_stack: pair record ", k, " has index ", pairs[std::size_t(k)].index));
  std::vector<const SliceOverride*> over(static_cast<std::size_t>(n), nullptr);
  for (const auto& o : options.overrides)
    if (o.index >= 0 && o.index < n) over[std::size_t(o.index)] = &o;
  if (options.anchor != "ct") return solve_without_ct(pairs, size, options, over);
  StackSolve result;
  result.frame = "ct";
  CtStackSolver solver(pairs, size, options, over, result);
  solver.solve();
  solver.write_slices();
  return result;
}

}  // namespace vispack::pipeline

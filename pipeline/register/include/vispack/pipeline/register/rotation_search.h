// The coarse rotation search shared by the pair estimate (register/pair.h) and the CT anchor's
// capture (register/ct_anchor.h): images rotated about their centre, a sweep of candidate angles
// scored by the caller, refined by half steps and a parabola. Angles in degrees,
// counter-clockwise as displayed (the convention of imaging/transforms.h). Pure and thread-safe.
#pragma once

#include <algorithm>
#include <vector>

#include <opencv2/core.hpp>

namespace vispack::pipeline {

// `image` rotated about its centre c = ((w−1)/2, (h−1)/2): out(x) = image(c + R(φ)(x − c)),
// linear interpolation, border replicated. φ = 0 returns `image` itself (shared data).
cv::Mat rotate_about_centre(const cv::Mat& image, double angle_deg);

// The rotation search's extent: angles −range_deg..range_deg in steps of step_deg.
struct RotationSweep {
  double range_deg = 10.0;
  double step_deg = 2.5;
};

// Evaluates `evaluate(angle_deg)` on the sweep's grid and returns the best candidate (highest
// `score`), refined: the two half steps around the grid's best are evaluated, a parabola through
// the three gives the peak (within half a step), which is kept when it scores at least as well
// as the three (less 1e-3); otherwise the best of the three. `Candidate` is what `evaluate`
// returns: any type with members `angle` and `score` (double).
template <class Evaluate>
auto sweep_rotation(const Evaluate& evaluate, RotationSweep sweep = {}) {
  using Candidate = decltype(evaluate(0.0));
  std::vector<Candidate> grid;
  for (double a = -sweep.range_deg; a <= sweep.range_deg + 1e-9; a += sweep.step_deg)
    grid.push_back(evaluate(a));
  std::size_t bi = 0;
  for (std::size_t i = 1; i < grid.size(); ++i)
    if (grid[i].score > grid[bi].score) bi = i;
  Candidate best = grid[bi];
  const double half = 0.5 * sweep.step_deg;
  const Candidate lo = evaluate(best.angle - half), hi = evaluate(best.angle + half);
  const double denom = lo.score - 2.0 * best.score + hi.score;
  double angle = best.angle;
  if (denom < 0.0) {
    angle += std::clamp(0.5 * (lo.score - hi.score) / denom, -0.5, 0.5) * half;
  } else if (lo.score > best.score || hi.score > best.score) {
    angle = lo.score > hi.score ? lo.angle : hi.angle;
  }
  if (angle != best.angle) {
    const Candidate refined = evaluate(angle);
    if (refined.score >= std::max(best.score, std::max(lo.score, hi.score)) - 1e-3) {
      best = refined;
    } else {
      best = lo.score > hi.score ? (lo.score > best.score ? lo : best)
                                 : (hi.score > best.score ? hi : best);
    }
  }
  return best;
}

}  // namespace vispack::pipeline

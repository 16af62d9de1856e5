// The CT anchor: each colour slice aligned to its own CT slice, an absolute (drift-free)
// measurement of its transform T_k (imaging/transforms.h: output point q appears in observed slice
// k at p = c + R(θ_k)(q − c) + d_k).
//
// The output grid is DEFINED by the CT (docs/ARCHITECTURE.md "The output frame"), never
// estimated: defined_ct_to_rgb(config). The anchor therefore estimates only T_k.
//
// Method (estimate_ct_anchor), on a working grid at CT resolution (the output grid scaled by
// anchor_scale = colour pixel / CT pixel, at most 1):
//   1. Template: the CT slice's body (outline.h ct_body_mask, grown by one CT pixel; the
//      head-holder or table around it, which the colour slice does not show, becomes air)
//      resampled onto the working output grid through ct_to_rgb (outside the CT: −1000 HU),
//      clamped to [−1000, 1000] HU. Its body (HU > hu_threshold) gives the body fraction and
//      the radius of gyration (the lever arm of the rotation).
//   2. Capture: soft body masks of both modalities (CT: HU around hu_threshold; colour:
//      distance from the gel colour, taken as the median of the slice border), each cut to ALL
//      its body parts by the part rule (outline.h body_parts; colour with its colour test, so
//      the green fiducial tubes take no part), at a level whose longer edge is about 128 px; at
//      rotations −10°..10° (step 2.5°, best refined by a parabola) two candidate shifts, phase
//      correlation and the largest overlap of the whole maps (a zero-padded correlation: every
//      part weighs its area), ranked by normalised correlation, then ECC (MOTION_EUCLIDEAN) on
//      the blurred masks. Without `initial` this runs always; with it, only if the refinement
//      from `initial` fails.
//   3. Refinement: a multimodal ECC. The colour → HU relation is unknown and not linear (gel,
//      fat, muscle, bone), so the colour slice is first mapped to a predicted CT: a quadratic
//      polynomial of (R, G, B) fitted by least squares to the template over the overlap at the
//      current alignment (the correlation ratio with a polynomial intensity function, a
//      standard multimodal measure). ECC (MOTION_EUCLIDEAN, sub-pixel) then aligns predicted
//      and CT; the polynomial is refitted and ECC repeated (half working resolution, then full).
//   4. Outline refinement: ECC of the two soft body masks (all body parts, as in step 2) at
//      full working resolution, from step 3's
//      result; kept when it converges within a few pixels and 1° of it. The outline is what both
//      modalities show alike; the intensity map of step 3 is not exact inside the body, which
//      biased a small body's rotation by tenths of a degree (docs/BENCHMARKS.md, 'Registration
//      anchored on the CT').
//   5. lever_px: how well the template pins rotation (below); correlation = the final ECC
//      coefficient; confidence = clamp((correlation − 0.4) / 0.4)
//      × clamp(body_fraction / 0.03): slices whose body is a small patch (the ends of the
//      stack) or whose match is poor get low confidence; none (body_fraction < 0.1 %) → not ok.
// Why every part takes part: below the pelvis a slice holds two legs of nearly the same size
// and shape. Matched part by part (each side reduced to its largest component, as before issue
// #30), the left leg of one image may pair with the right leg of the other: an alignment that
// is off by the legs' separation (hundreds of pixels) and correlates as well as the truth. A
// symmetric pair cannot capture the whole-slice match: shifting one image by the separation
// lays one leg on the other and leaves the second leg on gel, so at most half the body
// overlaps, while the true alignment overlaps both; the normalised correlation of the whole
// soft maps (capture) and ECC on them rank the true alignment first. Only a part the other
// modality lacks (a fiducial tube, a holder) could pull it, and the part rule removes those.
// Cost: about the cost of one pair estimate on a 2048×1216 slice with CT 2.8× coarser.
// All functions are pure and thread-safe.
#pragma once

#include <optional>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/frame.h"

namespace vispack::pipeline {

// The anchor's working scale for a config with CT: min(1, spacing_mm[0] / ct.pixel_spacing_mm[0])
// (the colour slice downsampled to about CT resolution). 0 without CT.
double anchor_working_scale(const Config& config);

struct AnchorOptions {
  double hu_threshold = -400.0;  // CT body threshold (mask.hu_threshold)
  int iterations = 50;           // ECC iteration limit per refinement pass
  // The part rule's minimum area in CT pixels (mask.min_part_mm2 / CT pixel area; outline.h).
  double min_part_ct_px = 0.0;
};

// One slice's CT anchor.
struct AnchorEstimate {
  bool ok = false;             // converged with body in view; false: confidence 0, no anchor term
  Rigid transform;             // T_k, full-resolution colour pixels
  double confidence = 0.0;     // [0, 1] (step 4 above)
  double correlation = 0.0;    // final ECC correlation coefficient of predicted vs CT
  double body_fraction = 0.0;  // CT body pixels / working-grid pixels
  double radius_px = 0.0;      // radius of gyration of the CT body, output (colour) pixels
  // The rotation's lever, output pixels: √(rotational / translational information) of the CT
  // template, Σ((x − m) × ∇T)² / (½ Σ|∇T|²) about the body's centroid m. About the radius for a
  // body with structure; → 0 for a featureless disk (the top of a head), whose rotation the
  // anchor cannot see.
  double lever_px = 0.0;
  // Nominal 1σ position error at confidence 1, colour pixels: the best case (0.05 working px);
  // the solve inflates it from the residuals where a stack's anchors do worse.
  double sigma_px = 0.0;
  // Body parts each modality showed (the part rule's kept parts of the soft body maps at their
  // half level; 0 where the anchor stopped before the capture). A count that changes abruptly
  // from one slice to the next marks a slice to look at (register/qc.h).
  int parts_ct = 0, parts_colour = 0;
};
nlohmann::json to_json(const AnchorEstimate& a);
// Throws FormatError naming `what` on a malformed record.
AnchorEstimate anchor_from_json(const nlohmann::json& j, const std::string& what);

// Aligns the colour slice of `frame` (its anchor_colour level must exist) to the CT slice
// `ct_hu` (CV_32F HU, CT pixels) for the output frame `ct_to_rgb`. `initial` (optional) is a
// starting T_k. Throws Error when the frame has no anchor level.
AnchorEstimate estimate_ct_anchor(const RegisterFrame& frame, const cv::Mat& ct_hu,
                                  const Similarity& ct_to_rgb, const AnchorOptions& options,
                                  const Rigid* initial = nullptr);

}  // namespace vispack::pipeline

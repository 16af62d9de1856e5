// Body masks (vispack-mask; docs/GOALS.md §1, §2, §6).
//
// The mask of output slice k comes from the CT, because colour thresholding alone fails in the
// translucent blue gel (tissue shows through it, fiducial tubes of another colour sit in it):
//   1. The CT at slice k's z in HU (slice_z.h): HU > L, the edge level L = mask_edge_level_hu:
//      mask.hu_threshold, but never above kAirTissueMidpointHu (−500 HU). On a CT slice, that
//      slice. Between two CT slices that show one body (the mask stage's choice, intermediates.h
//      CtSlice): with the gel refinement (step 4) the larger HU of the two, i.e. the union of
//      their outlines, where the body may be, for the colour to trim to where it is; without it
//      (mask.refine_gel false, a black colour slice) their outlines interpolated by signed
//      distance (ct_shape_blend.h). Not the HU blend: it keeps the nearer slice's outline until
//      half way, then jumps (docs/ARCHITECTURE.md "Each input at its own z").
//   2. Detach what merely touches the body (head-holder, table): an opening of radius
//      kCtDetachPx CT pixels (removes structures thinner than about 2·kCtDetachPx), every part
//      that is body by the part rule (outline.h: not smaller than mask.min_part_mm2, not thin and
//      long like a holder or table; never "the largest component": arms, two legs and toes are
//      several parts of one slice), then the threshold within kCtDetachPx + 1 of the kept parts
//      (restores their own edge; a holder or table touching the body, or separated from it and
//      touching it only through thin bridges, stays out); holes filled (lungs).
//      Steps 1–2 are ct_body_mask (outline.h), shared with registration.
//   3. Carried onto the output grid (the registered colour grid) through ct_to_rgb from
//      transforms.json with a sub-pixel edge: the output pixel is body where the CT's HU,
//      linearly interpolated, exceeds L. Step 2 still decides what is body: the edge moves only
//      between a CT pixel centre of its body and one outside it (one warp of a levels image that
//      holds the HU, clamped to its side of L, along the edge, and the band of step 4).
//   4. With mask.refine_gel: in a band 12 output pixels deep (at least one CT pixel) along the
//      edge of the carried CT mask, pixels of the registered colour slice that are gel
//      coloured (remove_edge_gel: closer than mask.gel_distance to the gel colour, or less
//      than half covered by tissue) and connected to the outside of the mask are removed: gel
//      the CT mask still covers at the edge, gel-filled notches. Gel-coloured pixels enclosed
//      by tissue, and anything deeper than the band, stay.
//   5. Where step 4 removed pixels: an opening of mask.opening_px output pixels (removing gel
//      connected to the outside opens no holes). Without refinement: the opening, the part
//      rule's minimum area and holes filled, on the carried CT mask.
// Without CT (no "ct" in the config, a slice beyond the CT stack, or a body's tip between a CT
// slice with body and one without) the mask is colour-only: distance to the gel > gel_distance,
// the opening, the part rule with its colour test (gel and green fiducial tubes are not
// tissue-coloured), holes filled; then step 4's test on its own edge band (always, whatever
// mask.refine_gel): the threshold keeps edge pixels barely covered by tissue and gel tinted by
// the tissue next to it (1 px too much all round, 11–15 % of a small section), so the edge pixels
// less than half covered that connect to the outside go.
//
// Where the edge was lost before (docs/BENCHMARKS.md, 'Mask edge against independent truth'): a CT
// edge is a partial-volume ramp (pixel size, PSF, and along z the slab over which a tapering
// outline changes), and the old mask took it at −400 HU — above the half-covered level, so inside
// the body, by ~0.25 px on the widest sections and by several pixels near the top of a head, where
// the slab smears the outline and a small cross-section's peak HU stays below −400 (no mask at
// all). The binary CT mask was then resampled, which quantises the edge to CT pixels (±1 output px
// at 2× coarser CT). The gel refinement only removes pixels, so it could not restore either loss.
// Now the CT edge lies at the half-covered level with sub-pixel placement (steps 1, 3): it errs
// outward, if at all, where the CT cannot place it (a smeared slab), and step 4 trims that on the
// colour edge. Measured on analytic head-cap stacks with a CT 2× coarser
// (tests/pipeline/test_mask_edge.cpp): mean edge offset −0.26 … −5 px → +0.02 … +0.12 px, IoU ≥
// 0.977 down to 500-px cross-sections. The opening (step 5) costs nothing measurable (≤ 0.001 IoU
// for radius 0…2). Without refinement (mask.refine_gel false, black slices) the CT alone sets the
// edge: within 0.05 px where the outline is steady along z, up to ~1–2 px outside on the smeared
// small sections of a head's top.
//
// Masks are CV_8UC1 with values 0 / 255. All functions here are pure and thread-safe (the
// stage, which sets OpenCV's process-wide thread count, is in mask_stage.h).
#pragma once

#include <optional>

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/imaging/outline.h"
#include "vispack/pipeline/imaging/transforms.h"

namespace vispack::pipeline {

// Step 4: removes from `mask` the gel-coloured pixels connected to its outside. A pixel is
// gel-coloured when its RGB distance to `gel` is below `distance` or below half the median
// distance of the mask's clearly non-gel pixels (an edge pixel less than half covered by
// tissue, even where tissue shows through the translucent gel next to it). With a non-empty
// `band` (0/255, same size) only pixels inside the band may be removed (and only those are
// examined). `removed` (optional) receives the bounding box of the removed pixels (empty if
// none). Throws Error on mismatched sizes or a mask that is not CV_8UC1.
cv::Mat remove_edge_gel(const cv::Mat& mask, const cv::Mat& rgb, const cv::Vec3f& gel,
                        double distance, const cv::Mat& band = cv::Mat(),
                        cv::Rect* removed = nullptr);

// The colour slice with the mask outline drawn in yellow (255, 255, 0), 1 px wide.
cv::Mat draw_mask_overlay(const cv::Mat& rgb, const cv::Mat& mask);

// One output slice's mask (steps 1–5). `rgb` is the registered colour slice (CV_8UC3, RGB);
// `ct_hu` (CV_32F HU, CT resolution) may be null for the colour-only mode, then `out_to_ct` is
// unused. `gel` overrides the estimate when set. Throws InputError on an unsupported image.
// `pixel_mm2`: the area of one output pixel in mm² (spacing_mm[0] · spacing_mm[1]), which turns
// mask.min_part_mm2 into pixels (CT pixels through out_to_ct's scale).
struct MaskSlice {
  cv::Mat mask;           // 0/255 on the output grid
  cv::Vec3f gel;          // the gel colour used
  double coverage = 0.0;  // fraction of mask pixels
  PartCounts parts;       // body parts kept and removed (CT parts where the CT decides)
};
// `z` (optional, with CT): the neighbouring CT slices along z, for the part rule's continuity
// (outline.h ZNeighbours): a part smaller than mask.min_part_mm2, or one the opening cut, that
// continues into them is body. Without refinement the output grid's minimum area still applies
// after the opening (docs/ARCHITECTURE.md "The body mask").
MaskSlice compute_mask(const cv::Mat& rgb, const cv::Mat* ct_hu, const cv::Matx23d& out_to_ct,
                       const MaskOptions& options, double pixel_mm2,
                       const ZNeighbours* z = nullptr);

}  // namespace vispack::pipeline

// Body masks (vispack-mask; DESIGN.md sections 1, 2, 7).
//
// The mask of output slice k comes from the CT, because colour thresholding alone fails in the
// translucent blue gel (tissue shows through it, fiducial tubes of another colour sit in it):
//   1. CT slice (k + ct.slice_offset) in HU: HU > mask.hu_threshold.
//   2. Detach what merely touches the body (head-holder, table): an opening of radius
//      kCtDetachPx CT pixels (removes structures thinner than about 2·kCtDetachPx), the largest
//      connected component, then the threshold restricted to that component grown by
//      kCtDetachPx + 1 (restores the body's own edge; a holder separated from the body by more
//      than that, touching it only through thin bridges, stays out); holes filled (lungs).
//   3. Resampled onto the output grid (the registered colour grid) through ct_to_rgb from
//      transforms.json: linear interpolation of the 0/255 mask, threshold at half.
//   4. With mask.refine_gel: in a band 12 output pixels deep (at least one CT pixel) along the
//      edge of the carried CT mask, pixels of the registered colour slice that are gel
//      coloured (remove_edge_gel: closer than mask.gel_distance to the gel colour, or less
//      than half covered by tissue) and connected to the outside of the mask are removed: gel
//      the CT mask still covers at the edge, gel-filled notches. Gel-coloured pixels enclosed
//      by tissue, and anything deeper than the band, stay.
//   5. Where step 4 removed pixels: an opening of mask.opening_px output pixels (removing gel
//      connected to the outside opens no holes). Without refinement: the opening, the largest
//      component and holes filled, on the carried CT mask.
// Without CT (no "ct" in the config, or a slice beyond the CT stack) the mask is colour-only:
// distance to the gel > gel_distance, then step 5.
//
// Masks are CV_8UC1 with values 0 / 255. All functions are pure and thread-safe.
#pragma once

#include <optional>

#include <opencv2/core.hpp>

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/stage.h"

namespace vispack::pipeline {

// Opening radius (CT pixels) that cuts a head-holder or table from the body in the CT.
inline constexpr int kCtDetachPx = 2;

// Largest 8-connected component of a 0/255 mask (empty mask → empty mask).
cv::Mat largest_component(const cv::Mat& mask);
// Fills holes: background not 4-connected to the image border becomes 255.
cv::Mat fill_holes(const cv::Mat& mask);
// Opening with a disc of `radius` pixels (radius 0: unchanged).
cv::Mat open_disc(const cv::Mat& mask, int radius);

// Steps 1–2 at CT resolution. `ct_hu`: CV_32F (or CV_16S) HU.
cv::Mat ct_body_mask(const cv::Mat& ct_hu, double hu_threshold);

// Median colour (RGB) of a 4-pixel frame along the border of an RGB CV_8UC3 slice.
cv::Vec3f estimate_gel_colour(const cv::Mat& rgb);
// 0/255 where the RGB colour is farther than `distance` from `gel`.
cv::Mat non_gel(const cv::Mat& rgb, const cv::Vec3f& gel, double distance);
// Colour-only body: non_gel, opening, largest component, holes filled.
cv::Mat colour_body_mask(const cv::Mat& rgb, const cv::Vec3f& gel, double distance, int opening_px);
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

// CT (CV_32F HU) resampled onto an output grid of `size`; `out_to_ct` maps output pixels to CT
// pixels (stage.h output_to_ct). Linear; outside the CT is −1024 HU (air).
cv::Mat resample_ct(const cv::Mat& ct_hu, const cv::Matx23d& out_to_ct, cv::Size size);
// A 0/255 mask resampled likewise (linear, threshold at 128).
cv::Mat resample_mask(const cv::Mat& mask, const cv::Matx23d& out_to_ct, cv::Size size);
// HU → CV_16U with value HU + 32768, clamped (the work/mask/ct_NNNN.png encoding).
cv::Mat encode_hu16(const cv::Mat& hu);

// The colour slice with the mask outline drawn in yellow (255, 255, 0), 1 px wide.
cv::Mat draw_mask_overlay(const cv::Mat& rgb, const cv::Mat& mask);

// One output slice's mask (steps 1–5). `rgb` is the registered colour slice (CV_8UC3, RGB);
// `ct_hu` (CV_32F HU, CT resolution) may be null for the colour-only mode, then `out_to_ct` is
// unused. `gel` overrides the estimate when set. Throws InputError on an unsupported image.
struct MaskSlice {
  cv::Mat mask;           // 0/255 on the output grid
  cv::Mat ct_hu;          // CV_32F HU on the output grid (empty in colour-only mode)
  cv::Vec3f gel;          // the gel colour used
  double coverage = 0.0;  // fraction of mask pixels
};
MaskSlice compute_mask(const cv::Mat& rgb, const cv::Mat* ct_hu, const cv::Matx23d& out_to_ct,
                       const MaskOptions& options);

// vispack-mask: for every output slice writes <work>/mask/mask_NNNN.png, overlay_NNNN.png,
// ct_NNNN.png (when CT is configured) and report.json (per-slice coverage, time, throughput).
// Reads <work>/register/transforms.json and the registered slices (run vispack-register first);
// per-slice work, so --slices shards freely.
StageResult run_mask_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

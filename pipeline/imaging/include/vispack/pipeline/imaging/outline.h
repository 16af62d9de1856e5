// Body and gel outlines shared by registration (register.h) and the body mask (mask.h).
//
// The body outline of a slice comes from either image:
//   - CT (ct_body_mask, at CT resolution): HU > threshold with its holes filled (a cavity near
//     the edge of a small body leaves a band of tissue thinner than the opening); an opening of
//     radius kCtDetachPx CT pixels detaches what merely touches the body (head-holder, table:
//     structures thinner than about 2·kCtDetachPx); the part rule below keeps every part that is
//     body; then what the opening shaved off the kept parts' own edge comes back: the threshold
//     within kCtDetachPx + 1 of a kept part, except a piece of the shaved-off set that reaches
//     farther than kHolderReachPx from every kept part (a holder or table touching the body, or
//     a holder separated from it and touching it only through thin bridges, stays out); holes
//     filled (lungs).
//   - colour (colour_body_mask): pixels farther than a colour distance from the gel colour
//     (estimate_gel_colour: the median of the slice's border frame), an opening, holes filled,
//     the part rule with its colour test.
//
// The part rule (body_parts): EVERY body part is body. A real axial slice holds several parts
// (arms beside the torso, two legs, two feet, toes, separate lobes at the top of a head), of
// nearly equal size below the pelvis: ranking parts by size (keeping the largest component, the
// rule before every part was body, docs/ARCHITECTURE.md, 'The body mask: every part is body') drops
// arms and a leg. A connected part (8-connected, after the opening, holes filled) is removed only
// by what tells it apart from tissue:
//   - debris: smaller than the minimum part area (config mask.min_part_mm2, converted to pixels
//     of the image by the caller). A part narrower than the opening is gone before the rule.
//   - holder, table, tube walls, cables: thin and long. Elongation = area / (π r²), r the part's
//     largest inscribed radius (the maximum of its distance transform): 1 for a disc, a/b for an
//     ellipse, 4L/(π t) for a band of length L and thickness t. Body cross-sections are compact
//     (torso 1.5–2.5, a foot's sole plane about 3, a finger about 1); a head-holder arc or a
//     table is a band (10 and more). Parts above kMaxPartElongation are removed, except in the
//     CT a part whose median HU is soft tissue's (≤ kSoftTissueMaxHu: holders and tables are
//     plastic, 130–300 HU in the head CT, 200 in the phantoms) and that is not a band
//     (elongation ≤ kMaxTissueElongation): a real brain's cerebellum is a crescent of
//     elongation 7.4, brain tissue at 30 HU. In the CT, a
//     thin spot of a band that the opening left (inscribed radius ≤ kCtDetachPx + 1.5) and that
//     touches a shaved-off piece larger than itself is a fragment of that band: removed.
//   - colour (colour only, when the slice is given): tissue in a cryosection is red, pink, cream,
//     brown or white, never bluer or greener than it is red: a part whose mean colour has
//     G > R + kTissueColourSlack or B > R + kTissueColourSlack (gel, green fiducial tubes) is
//     removed.
//   - continuity along z (CT, where the caller gives the neighbouring CT slices: ZNeighbours): a
//     part of the threshold (holes filled) that the opening or the minimum area dropped, apart
//     from the kept parts, is body when it continues along z: at least a quarter of its pixels
//     lie on tissue (HU above the level, holes filled) in enough of the neighbouring CT slices
//     (one of the two beside a CT slice; both CT slices a slice between them is blended from),
//     and it is not thin and long. A finger tip or a toe of a few mm² continues into its
//     neighbours; a speck of one CT slice (noise, a crumb) does not and goes. The minimum area
//     is the fallback where no neighbour is given (the anchor's template, colour-only masks).
//
// Masks are CV_8UC1 with values 0 / 255; colour slices are CV_8UC3 in RGB order; distances in
// RGB units (0..255 per channel); radii in pixels of the image they are given. All functions are
// pure (inputs are not modified, results are new images) and thread-safe.
#pragma once

#include <vector>

#include <opencv2/core.hpp>

namespace vispack::pipeline {

// Opening radius (CT pixels) that cuts a head-holder or table from the body in the CT.
inline constexpr int kCtDetachPx = 2;

// Half way between air (−1000 HU) and soft tissue (about 0 HU: fat −100, skin and muscle +40):
// where a CT pixel is half covered by the body.
inline constexpr double kAirTissueMidpointHu = -500.0;
// The HU level at which the mask's edge is placed (the mask stage, and the CT blend's check of
// a body's tip): mask.hu_threshold, but never above kAirTissueMidpointHu (a higher level puts the
// edge inside the partial-volume band).
inline double mask_edge_level_hu(double hu_threshold) {
  return hu_threshold < kAirTissueMidpointHu ? hu_threshold : kAirTissueMidpointHu;
}
// A piece the opening removed that reaches farther than this (CT pixels) from every kept part is
// a holder or table touching the body: none of it comes back.
inline constexpr int kHolderReachPx = 3 * (kCtDetachPx + 1);
// Parts more elongated than this (area / (π r²), r the largest inscribed radius) are holders.
inline constexpr double kMaxPartElongation = 7.0;
// A CT part more elongated than kMaxPartElongation is still body when its median HU is at most
// this (fat, muscle, brain; holders and tables are denser plastic) and its elongation at most
// kMaxTissueElongation (a band of tissue-like HU, a gel pad or a cable, is not body).
inline constexpr double kSoftTissueMaxHu = 100.0;
inline constexpr double kMaxTissueElongation = 2.0 * kMaxPartElongation;
// RGB units by which a tissue part's mean green or blue may exceed its mean red.
inline constexpr double kTissueColourSlack = 10.0;

// What the part rule keeps. `min_area_px`: parts with fewer pixels are removed (0: none);
// `max_elongation`: parts above are removed (0: no shape test).
struct PartRule {
  double min_area_px = 0.0;
  double max_elongation = kMaxPartElongation;
};
// Parts of one slice kept and removed by the rule (for the stage reports).
struct PartCounts {
  int kept = 0;
  int removed = 0;
};
// The part rule (above) on a 0/255 mask: every 8-connected part that passes is kept. The shape
// test reads the parts' outlines: fill their holes first (fill_holes). With a
// non-empty `rgb` (CV_8UC3, same size) the colour test applies too; with a non-empty `hu`
// (CV_32F HU, same size: the CT) an elongated part of soft tissue's HU stays. `counts`
// (optional) receives the parts kept and removed. Throws Error when `rgb` or `hu` differs in
// size.
cv::Mat body_parts(const cv::Mat& mask, const PartRule& rule, PartCounts* counts = nullptr,
                   const cv::Mat& rgb = cv::Mat(), const cv::Mat& hu = cv::Mat());
// Fills holes: background not 4-connected to the image border becomes 255.
cv::Mat fill_holes(const cv::Mat& mask);
// Opening with a disc of `radius` pixels (radius 0: unchanged).
cv::Mat open_disc(const cv::Mat& mask, int radius);

// A single-channel CT slice (CV_32F, CV_16S, …) as CV_32F HU (CV_32F input is returned, not
// copied). Throws InputError for a multi-channel image.
cv::Mat ct_hu_float(const cv::Mat& ct_hu);
// Throws InputError naming `what` unless `rgb` is a non-empty CV_8UC3 image.
void require_rgb_slice(const cv::Mat& rgb, const char* what);

// The CT slices next to one along z, for the continuity rule (above): the tissue of each (0/255,
// the CT slice's size: HU above the level, holes filled; ct_tissue) and how many of them a small
// part must continue into. Beside CT slice j: slices j − 1 and j + 1 (those that exist), needed
// 1; a slice blended between CT slices a and b: a and b, needed 2 (a part of one CT slice only,
// which the blend carries half way to the next, is still a speck).
struct ZNeighbours {
  std::vector<cv::Mat> tissue;
  int needed = 1;
};
// The tissue of a CT slice for ZNeighbours: HU above `hu_threshold`, holes filled.
cv::Mat ct_tissue(const cv::Mat& ct_hu, double hu_threshold);

// The body at CT resolution (see above). `ct_hu`: CV_32F (or CV_16S) HU; `min_part_px`: the
// minimum part area in CT pixels (mask.min_part_mm2 / CT pixel area); `counts` (optional): the
// parts kept and removed by the rule (a part kept for its continuity counts as kept);
// `z` (optional): the neighbouring CT slices (continuity along z). Throws Error when a
// neighbour's size differs from the slice's.
cv::Mat ct_body_mask(const cv::Mat& ct_hu, double hu_threshold, double min_part_px,
                     PartCounts* counts = nullptr, const ZNeighbours* z = nullptr);

// Median colour (RGB) of a 4-pixel frame along the border of an RGB CV_8UC3 slice.
cv::Vec3f estimate_gel_colour(const cv::Mat& rgb);
// 0/255 where the RGB colour is farther than `distance` from `gel`.
cv::Mat non_gel(const cv::Mat& rgb, const cv::Vec3f& gel, double distance);
// Colour-only body: non_gel, opening, holes filled, the part rule with the colour test
// (`min_part_px` in pixels of `rgb`). `counts` (optional): the parts kept and removed.
cv::Mat colour_body_mask(const cv::Mat& rgb, const cv::Vec3f& gel, double distance, int opening_px,
                         double min_part_px, PartCounts* counts = nullptr);

}  // namespace vispack::pipeline

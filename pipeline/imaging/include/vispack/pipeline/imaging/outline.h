// Body and gel outlines shared by registration (register.h) and the body mask (mask.h).
//
// The body outline of a slice comes from either image:
//   - CT (ct_body_mask, at CT resolution): HU > threshold with its holes filled (a cavity near
//     the edge of a small body leaves a band of tissue thinner than the opening); an opening of
//     radius kCtDetachPx CT pixels detaches what merely touches the body (head-holder, table:
//     structures thinner than about 2·kCtDetachPx), the largest connected component is the body,
//     then the threshold is restricted to that component grown by kCtDetachPx + 1 (restores the
//     body's own edge; a holder separated from the body by more than that, touching it only through
//     thin bridges, stays out); holes filled (lungs).
//   - colour (colour_body_mask): pixels farther than a colour distance from the gel colour
//     (estimate_gel_colour: the median of the slice's border frame), an opening, the largest
//     component, holes filled.
//
// Masks are CV_8UC1 with values 0 / 255; colour slices are CV_8UC3 in RGB order; distances in
// RGB units (0..255 per channel); radii in pixels of the image they are given. All functions are
// pure (inputs are not modified, results are new images) and thread-safe.
#pragma once

#include <opencv2/core.hpp>

namespace vispack::pipeline {

// Opening radius (CT pixels) that cuts a head-holder or table from the body in the CT.
inline constexpr int kCtDetachPx = 2;

// Largest 8-connected component of a 0/255 mask (empty mask → empty mask).
cv::Mat largest_component(const cv::Mat& mask);
// Fills holes: background not 4-connected to the image border becomes 255.
cv::Mat fill_holes(const cv::Mat& mask);
// Opening with a disc of `radius` pixels (radius 0: unchanged).
cv::Mat open_disc(const cv::Mat& mask, int radius);

// A single-channel CT slice (CV_32F, CV_16S, …) as CV_32F HU (CV_32F input is returned, not
// copied). Throws InputError for a multi-channel image.
cv::Mat ct_hu_float(const cv::Mat& ct_hu);
// Throws InputError naming `what` unless `rgb` is a non-empty CV_8UC3 image.
void require_rgb_slice(const cv::Mat& rgb, const char* what);

// The body at CT resolution (see above). `ct_hu`: CV_32F (or CV_16S) HU.
cv::Mat ct_body_mask(const cv::Mat& ct_hu, double hu_threshold);

// Median colour (RGB) of a 4-pixel frame along the border of an RGB CV_8UC3 slice.
cv::Vec3f estimate_gel_colour(const cv::Mat& rgb);
// 0/255 where the RGB colour is farther than `distance` from `gel`.
cv::Mat non_gel(const cv::Mat& rgb, const cv::Vec3f& gel, double distance);
// Colour-only body: non_gel, opening, largest component, holes filled.
cv::Mat colour_body_mask(const cv::Mat& rgb, const cv::Vec3f& gel, double distance, int opening_px);

}  // namespace vispack::pipeline

// The CT's body outline between two CT slices along z: a shape-based interpolation (signed
// distances to the outline blended), for the body mask of a colour slice that lies between two
// CT slices (docs/ARCHITECTURE.md "Each input at its own z" says why not linear in HU).
// Thread-safe: pure functions. Units: CT pixels and HU.
#pragma once

#include <opencv2/core.hpp>

namespace vispack::pipeline {

// The signed distance (CT pixels, negative inside) from every pixel centre of `hu` (CV_32F HU,
// CT resolution) to its outline at `level` (HU > level is inside). Pixels with an 8-neighbour on
// the other side (the edge) take the sub-pixel distance from their own HU and the local HU slope
// (level − HU) / |∇HU|, kept within one pixel on their side; the others their distance to the
// nearest pixel of the other side less half a pixel. A slice with no pixel on one side: ±1e4.
cv::Mat outline_distance(const cv::Mat& hu, double level);

// The CT for the body mask at `w_above` (0..1) of the way from `hu_below` to `hu_above` (CV_32F
// HU, one size): its outline at `level` is the zero crossing of the two slices' outline_distance
// blended linearly (a growing or shrinking outline moves steadily; the HU blend keeps it at the
// nearer slice's outline until half way and then jumps). Pixels within one pixel of that outline
// hold level − kShapeSlopeHuPerPx · distance (the mask's sub-pixel edge reads the outline from
// them, mask.h step 3); the others the HU blended linearly when it lies on the same side of
// `level`, else the same level − slope · distance. Both slices without body (or all body): the
// HU blend. Throws Error on mismatched sizes or types.
inline constexpr double kShapeSlopeHuPerPx = 500.0;
cv::Mat shape_blend_hu(const cv::Mat& hu_below, const cv::Mat& hu_above, double w_above,
                       double level);

}  // namespace vispack::pipeline

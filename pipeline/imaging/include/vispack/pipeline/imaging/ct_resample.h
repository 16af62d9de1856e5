// A CT slice on the output grid, and the 16-bit encoding of HU the work folder and the packed
// file's ct channel use. Thread-safe: pure functions.
#pragma once

#include <opencv2/core.hpp>

namespace vispack::pipeline {

// CT (CV_32F HU) resampled onto an output grid of `size`; `out_to_ct` maps output pixels to CT
// pixels (imaging/transforms.h output_to_ct). Linear; outside the CT is −1024 HU (air).
cv::Mat resample_ct(const cv::Mat& ct_hu, const cv::Matx23d& out_to_ct, cv::Size size);
// HU → CV_16U with value HU + 32768, clamped (the work/mask/ct_NNNN.png encoding).
cv::Mat encode_hu16(const cv::Mat& hu);

}  // namespace vispack::pipeline

// resample_ct and encode_hu16 (ct_resample.h).
#include "vispack/pipeline/imaging/ct_resample.h"

#include "vispack/pipeline/imaging/outline.h"

#include <opencv2/imgproc.hpp>

namespace vispack::pipeline {

cv::Mat resample_ct(const cv::Mat& ct_hu, const cv::Matx23d& out_to_ct, cv::Size size) {
  cv::Mat out;
  cv::warpAffine(ct_hu_float(ct_hu), out, cv::Mat(out_to_ct), size,
                 cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT, cv::Scalar(-1024));
  return out;
}

cv::Mat encode_hu16(const cv::Mat& hu) {
  cv::Mat out;
  ct_hu_float(hu).convertTo(out, CV_16U, 1.0, 32768.0);  // saturating: clamps to 0..65535
  return out;
}

}  // namespace vispack::pipeline

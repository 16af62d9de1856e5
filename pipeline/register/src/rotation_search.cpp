// Rotation search helpers. See register/rotation_search.h.
#include "vispack/pipeline/register/rotation_search.h"

#include <opencv2/imgproc.hpp>

#include "vispack/pipeline/imaging/transforms.h"

namespace vispack::pipeline {

cv::Mat rotate_about_centre(const cv::Mat& image, double angle_deg) {
  if (angle_deg == 0.0) return image;
  cv::Mat out;
  cv::warpAffine(image, out, cv::Mat(rigid_matrix({angle_deg, 0, 0}, image_centre(image.size()))),
                 image.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
  return out;
}

}  // namespace vispack::pipeline

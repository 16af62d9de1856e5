#include "vispack/pipeline/imaging/opencv_threads.h"

#include <opencv2/core.hpp>

namespace vispack::pipeline {

ScopedOpenCvThreads::ScopedOpenCvThreads(int threads) : previous_(cv::getNumThreads()) {
  cv::setNumThreads(threads);
}
ScopedOpenCvThreads::~ScopedOpenCvThreads() {
  cv::setNumThreads(previous_);
}

}  // namespace vispack::pipeline

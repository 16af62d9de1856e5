// OpenCV's process-wide thread count, set for a scope.
#pragma once

namespace vispack::pipeline {

// Sets OpenCV's own thread count for this object's lifetime (restored on destruction): stages
// that spread slices over their own workers switch OpenCV's pool off to avoid oversubscription.
// Not thread-safe (OpenCV's setting is process-wide): construct it on the stage's calling thread.
class ScopedOpenCvThreads {
 public:
  explicit ScopedOpenCvThreads(int threads);
  ~ScopedOpenCvThreads();
  ScopedOpenCvThreads(const ScopedOpenCvThreads&) = delete;
  ScopedOpenCvThreads& operator=(const ScopedOpenCvThreads&) = delete;

 private:
  int previous_;
};

}  // namespace vispack::pipeline

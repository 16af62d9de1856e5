#include "vispack/pipeline/core/version.h"

// VISPACK_VERSION comes from project(VERSION ...) in the top-level CMakeLists.txt.
#ifndef VISPACK_VERSION
#error "VISPACK_VERSION must be defined by the build (pipeline/CMakeLists.txt)"
#endif

namespace vispack {
const char* version_string() {
  return VISPACK_VERSION;
}
}  // namespace vispack

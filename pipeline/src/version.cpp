#include "vispack/pipeline/version.h"

namespace vispack {
const char* version_string() { return "0.1.0"; }
}  // namespace vispack

// vispack's version and build identity, recorded in reports and packed-file provenance.
#pragma once

namespace vispack {
const char* version_string();  // project(VERSION) of the top-level CMakeLists.txt, e.g. "0.1.0"
}

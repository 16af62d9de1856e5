// format_make_sample OUT.vpk: writes a small deterministic packed volume (40 x 30 x 20 voxels,
// rgba + ct + labels, brick edge 16) for tests that need a file without the pipeline (the
// install/consumer test).
#include <cstdio>
#include <exception>

#include "format_test_util.h"

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: format_make_sample OUT.vpk\n");
    return 2;
  }
  try {
    using namespace vispack::format::testing;
    Volume v = make_volume({40, 30, 20}, 5);
    write(argv[1], v, options_for(v, 16));
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "format_make_sample: error: %s\n", e.what());
    return 1;
  }
}

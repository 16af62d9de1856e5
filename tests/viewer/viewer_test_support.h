// Shared by the viewer's GL tests: a headless GL context (re-running the test binary under
// xvfb-run when no EGL platform works); writing a VolumeData as a packed file (packed_volume.h).
#pragma once

#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include "../render/packed_volume.h"
#include "vispack/viewer/context.h"

namespace vispack::test {

// A headless GL context (EGL without a display). If none can be made, the test binary re-runs
// itself once under `xvfb-run -a` (`argv`: its own command line; does not return when it can);
// if that fails too, returns null and every test fails in its SetUp.
inline std::unique_ptr<viewer::HeadlessContext> make_gl_context(const std::vector<char*>& argv) {
  try {
    return std::make_unique<viewer::HeadlessContext>();
  } catch (const std::exception& e) {
    std::cerr << "headless EGL failed: " << e.what() << "\n";
    if (!std::getenv("VISPACK_XVFB_RETRY") && !argv.empty()) {
      std::cerr << "retrying under xvfb-run -a\n";
      setenv("VISPACK_XVFB_RETRY", "1", 1);
      std::vector<char*> args = {const_cast<char*>("xvfb-run"), const_cast<char*>("-a")};
      args.insert(args.end(), argv.begin(), argv.end());
      args.push_back(nullptr);
      std::fflush(nullptr);
      execvp("xvfb-run", args.data());
      std::cerr << "cannot run xvfb-run\n";
    }
    return nullptr;
  }
}

}  // namespace vispack::test

// The one exit-code table shared by every vispack executable (documented in README.md).
#pragma once

#include <exception>

namespace vispack {

enum class ExitCode : int {
  kSuccess = 0,
  kFailure = 1,       // runtime failure not covered below (a bug, out of memory)
  kUsage = 2,         // bad command line
  kIo = 3,            // cannot read or write a file
  kInvalidFile = 4,   // a file is corrupt, truncated or hostile; --verify found a bad brick
  kConfig = 5,        // invalid configuration
  kInput = 6,         // unusable input slices
  kBusy = 7,          // the work folder is in use by another run (pipeline/core/work_lock.h)
  kInterrupted = 130  // SIGINT
};

// Maps an exception (vispack::Error subclasses included) to its exit code.
ExitCode exit_code_for(const std::exception& error) noexcept;

}  // namespace vispack

// BusyError: a resource another process holds, the work folder of a run (pipeline/core/
// work_lock.h). Exit code 7 (exit_codes.h). Kept beside error.h's classes, which every file
// includes, because only the lock and the exit-code mapping need it.
#pragma once

#include "vispack/common/error.h"

namespace vispack {

// The work folder is in use by another run (its lock is held). Exit code 7.
class BusyError : public Error {
 public:
  using Error::Error;
};

}  // namespace vispack

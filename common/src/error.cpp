#include "vispack/common/error.h"

#include <new>

#include "vispack/common/busy_error.h"
#include "vispack/common/exit_codes.h"

namespace vispack {

ExitCode exit_code_for(const std::exception& error) noexcept {
  if (dynamic_cast<const UsageError*>(&error)) return ExitCode::kUsage;
  if (dynamic_cast<const IoError*>(&error)) return ExitCode::kIo;
  if (dynamic_cast<const FormatError*>(&error)) return ExitCode::kInvalidFile;
  if (dynamic_cast<const ConfigError*>(&error)) return ExitCode::kConfig;
  if (dynamic_cast<const InputError*>(&error)) return ExitCode::kInput;
  if (dynamic_cast<const BusyError*>(&error)) return ExitCode::kBusy;
  return ExitCode::kFailure;
}

}  // namespace vispack

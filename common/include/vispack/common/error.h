// Error types shared by every vispack library and executable.
//
// Every error carries its context in the message: the file, slice, key or brick at fault.
// Build messages with vispack::cat(...), which streams its arguments into one string:
//   throw vispack::IoError(vispack::cat(path, ": cannot open: ", std::strerror(errno)));
// Each error class maps to one exit code (exit_codes.h), so executables only need to catch
// std::exception at the top (see cli.h: run_main).
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>

namespace vispack {

// Streams all arguments into one string (operator<< must exist for each).
template <class... Args>
std::string cat(Args&&... args) {
  std::ostringstream out;
  (out << ... << std::forward<Args>(args));
  return out.str();
}

// Base class of every vispack error.
class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Wrong command-line usage (unknown flag, missing argument, bad value). Exit code 2.
class UsageError : public Error {
 public:
  using Error::Error;
};

// Operating-system level I/O failure: open, read, write, rename, mmap, disk full. Exit code 3.
class IoError : public Error {
 public:
  using Error::Error;
};

// A file exists and was read, but its content is not valid (bad magic, checksum mismatch,
// truncated, hostile sizes, malformed JSON in a packed file). Exit code 4.
class FormatError : public Error {
 public:
  using Error::Error;
};

// A configuration file is invalid: unknown key, wrong type, missing folder. Exit code 5.
class ConfigError : public Error {
 public:
  using Error::Error;
};

// Input slices are unusable: wrong size, unreadable image, unknown colour in strict mode. Exit 6.
class InputError : public Error {
 public:
  using Error::Error;
};

}  // namespace vispack

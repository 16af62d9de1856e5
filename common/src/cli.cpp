#include "vispack/common/cli.h"

#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <sstream>

#include "vispack/common/error.h"
#include "vispack/common/exit_codes.h"

namespace vispack {
namespace {

// Thrown by Args::done() when --help was given: run_main prints usage and returns 0.
struct HelpRequested {
  std::string text;
};

bool starts_with(const std::string& s, const std::string& prefix) {
  return s.compare(0, prefix.size(), prefix) == 0;
}

}  // namespace

Args::Args(std::string program, int argc, char** argv) : program_(std::move(program)) {
  for (int i = 1; i < argc; ++i)
    args_.emplace_back(argv[i]);
  used_.assign(args_.size(), false);
  for (std::size_t i = 0; i < args_.size(); ++i) {
    if (args_[i] == "--help" || args_[i] == "-h") {
      help_requested_ = true;
      used_[i] = true;
    }
  }
}

void Args::describe(std::string synopsis, std::string description) {
  synopsis_ = std::move(synopsis);
  description_ = std::move(description);
}

bool Args::flag(const std::string& name, const std::string& help) {
  help_lines_.push_back(cat("  ", name, "\n      ", help));
  bool found = false;
  for (std::size_t i = 0; i < args_.size(); ++i) {
    if (!used_[i] && args_[i] == name) {
      used_[i] = true;
      found = true;
    }
  }
  return found;
}

std::optional<std::string> Args::option(const std::string& name, const std::string& meta,
                                        const std::string& help) {
  help_lines_.push_back(cat("  ", name, " ", meta, "\n      ", help));
  std::optional<std::string> value;
  for (std::size_t i = 0; i < args_.size(); ++i) {
    if (used_[i]) continue;
    if (args_[i] == name) {
      used_[i] = true;
      if (i + 1 >= args_.size() || used_[i + 1]) {
        if (help_requested_) return std::nullopt;
        throw UsageError(cat(name, " needs a value (", meta, ")"));
      }
      used_[i + 1] = true;
      value = args_[i + 1];
      ++i;
    } else if (starts_with(args_[i], name + "=")) {
      used_[i] = true;
      value = args_[i].substr(name.size() + 1);
    }
  }
  return value;
}

std::string Args::option(const std::string& name, const std::string& meta, const std::string& help,
                         const std::string& default_value) {
  auto value = option(name, meta, cat(help, " (default: ", default_value, ")"));
  return value ? *value : default_value;
}

std::optional<long long> Args::option_int(const std::string& name, const std::string& meta,
                                          const std::string& help) {
  auto text = option(name, meta, help);
  if (!text) return std::nullopt;
  char* end = nullptr;
  errno = 0;
  long long value = std::strtoll(text->c_str(), &end, 10);
  if (text->empty() || *end != '\0' || errno == ERANGE) {
    throw UsageError(cat(name, ": '", *text, "' is not an integer"));
  }
  return value;
}

std::optional<double> Args::option_double(const std::string& name, const std::string& meta,
                                          const std::string& help) {
  auto text = option(name, meta, help);
  if (!text) return std::nullopt;
  char* end = nullptr;
  double value = std::strtod(text->c_str(), &end);
  if (text->empty() || *end != '\0') {
    throw UsageError(cat(name, ": '", *text, "' is not a number"));
  }
  return value;
}

std::string Args::positional(const std::string& meta, const std::string& help, bool optional) {
  help_lines_.push_back(cat("  ", meta, "\n      ", help));
  for (std::size_t i = 0; i < args_.size(); ++i) {
    if (used_[i]) continue;
    if (starts_with(args_[i], "-") && args_[i] != "-") continue;
    used_[i] = true;
    return args_[i];
  }
  // Reported by done(), after unknown options: "vispack-info --bogus" names --bogus, not FILE.
  if (!optional && missing_.empty()) missing_ = meta;
  return {};
}

std::string Args::usage() const {
  std::string text = cat("usage: ", program_, " ", synopsis_, "\n\n", description_, "\n\n");
  for (const auto& line : help_lines_)
    text += line + "\n";
  text += "  --help\n      print this help and exit\n";
  return text;
}

void Args::done() {
  if (help_requested_) throw HelpRequested{usage()};
  for (std::size_t i = 0; i < args_.size(); ++i) {
    if (!used_[i]) {
      if (starts_with(args_[i], "-"))
        throw UsageError(cat("unknown option ", args_[i], " (see --help)"));
      throw UsageError(cat("unexpected argument '", args_[i], "' (see --help)"));
    }
  }
  if (!missing_.empty()) throw UsageError(cat("missing ", missing_, " (see --help)"));
}

SliceRange parse_slice_range(const std::string& text, int count) {
  auto colon = text.find(':');
  if (colon == std::string::npos) throw UsageError(cat("--slices '", text, "' is not A:B"));
  auto parse = [&](const std::string& part, int fallback) {
    if (part.empty()) return fallback;
    char* end = nullptr;
    long value = std::strtol(part.c_str(), &end, 10);
    if (*end != '\0' || value < 0)
      throw UsageError(cat("--slices '", text, "': bad bound '", part, "'"));
    return int(std::min<long>(value, count));
  };
  SliceRange range{parse(text.substr(0, colon), 0), parse(text.substr(colon + 1), count)};
  if (range.first > range.last) throw UsageError(cat("--slices '", text, "': empty range"));
  return range;
}

int run_main(const std::string& program, int argc, char** argv,
             const std::function<int(Args&)>& body) {
  try {
    Args args(program, argc, argv);
    return body(args);
  } catch (const HelpRequested& help) {
    std::cout << help.text;
    return 0;
  } catch (const std::bad_alloc&) {
    std::cerr << program << ": error: out of memory\n";
    return int(ExitCode::kFailure);
  } catch (const std::exception& error) {
    // A message of several lines (a config with several errors) prints one error line each.
    std::istringstream lines(error.what());
    std::string line;
    bool printed = false;
    while (std::getline(lines, line)) {
      std::cerr << program << ": error: " << line << "\n";
      printed = true;
    }
    if (!printed) std::cerr << program << ": error: (no message)\n";
    return int(exit_code_for(error));
  }
}

}  // namespace vispack

// Command-line parsing and the top-level error handler shared by every executable.
//
// Usage shape of a vispack executable (about a screen of code):
//   int main(int argc, char** argv) {
//     return vispack::run_main("vispack-info", argc, argv, [](vispack::Args& args) {
//       args.describe("FILE [--json] [--verify]", "Prints a packed volume's metadata.");
//       bool json = args.flag("--json", "print JSON instead of text");
//       std::string file = args.positional("FILE", "packed volume");
//       args.done();           // --help prints usage and exits 0; leftovers are a UsageError
//       ...
//       return 0;
//     });
//   }
// Errors are printed as one line, "<program>: error: <message>" (one such line per line of a
// message that holds several, e.g. every error of a config file), and mapped to exit codes
// (exit_codes.h).
#pragma once

#include <functional>
#include <optional>
#include <string>
#include <vector>

namespace vispack {

class Args {
 public:
  Args(std::string program, int argc, char** argv);

  // One-line synopsis after the program name, and a paragraph of description.
  void describe(std::string synopsis, std::string description);
  // A boolean flag such as "--json".
  bool flag(const std::string& name, const std::string& help);
  // An option with a value: "--level 2" or "--level=2". Returns nullopt when absent.
  std::optional<std::string> option(const std::string& name, const std::string& meta,
                                    const std::string& help);
  // Same, with a default that --help shows.
  std::string option(const std::string& name, const std::string& meta, const std::string& help,
                     const std::string& default_value);
  // Typed helpers; a value that does not parse is a UsageError naming the option.
  std::optional<long long> option_int(const std::string& name, const std::string& meta,
                                      const std::string& help);
  std::optional<double> option_double(const std::string& name, const std::string& meta,
                                      const std::string& help);
  // Next positional argument (required unless `optional`); empty string when absent (a missing
  // required one is reported by done(), after any unknown option).
  std::string positional(const std::string& meta, const std::string& help, bool optional = false);
  // Call after declaring everything: handles --help (prints usage, exits 0) and rejects
  // unknown flags or extra arguments with a UsageError.
  void done();

  std::string usage() const;
  const std::string& program() const { return program_; }

 private:
  std::string program_, synopsis_, description_;
  std::vector<std::string> args_;
  std::vector<bool> used_;
  std::vector<std::string> help_lines_;
  bool help_requested_ = false;
  std::string missing_;  // meta of the first required positional argument that is absent
};

// Parses "A:B" (half-open slice range; either side may be empty) into [first, last).
// `count` is the number of slices; the result is clamped to it. Throws UsageError.
struct SliceRange {
  int first = 0;
  int last = 0;  // exclusive
  int size() const { return last - first; }
  bool contains(int i) const { return i >= first && i < last; }
};
SliceRange parse_slice_range(const std::string& text, int count);

// Runs `body`, catching every exception, printing "<program>: error: <what>" to stderr and
// returning the exit code for it. Returns body's return value otherwise.
int run_main(const std::string& program, int argc, char** argv,
             const std::function<int(Args&)>& body);

}  // namespace vispack

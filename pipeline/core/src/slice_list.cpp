// list_slices (slice_list.h): a slice folder's files by number.
#include <algorithm>
#include <filesystem>
#include <system_error>
#include <vector>

#include "vispack/common/error.h"
#include "vispack/pipeline/core/slice_list.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

std::vector<SliceFile> list_slices(const SliceSource& source) {
  const std::string& pattern = source.pattern;
  const auto token = pattern.find("{n}");
  if (token == std::string::npos || pattern.find("{n}", token + 1) != std::string::npos) {
    throw ConfigError(
        cat("pattern \"", pattern, "\" for folder ", source.dir, " must contain {n} exactly once"));
  }
  const std::string prefix = pattern.substr(0, token);
  // {a} right after {n}: one letter orders the files of one number (slice_io.h).
  const bool lettered = pattern.compare(token + 3, 3, "{a}") == 0;
  const std::string suffix = pattern.substr(token + (lettered ? 6 : 3));
  if (suffix.find("{a}") != std::string::npos || prefix.find("{a}") != std::string::npos) {
    throw ConfigError(cat("pattern \"", pattern, "\" for folder ", source.dir,
                          ": {a} (a letter) must follow {n} directly"));
  }
  std::error_code ec;
  if (!fs::is_directory(source.dir, ec)) {
    throw ConfigError(
        cat("slice folder ", source.dir, " does not exist (pattern \"", pattern, "\")"));
  }
  std::vector<SliceFile> files;
  fs::directory_iterator it(source.dir, ec);
  if (ec) {
    throw ConfigError(cat("cannot list slice folder ", source.dir, ": ", ec.message()));
  }
  for (; it != fs::directory_iterator(); it.increment(ec)) {
    if (ec) throw ConfigError(cat("cannot list slice folder ", source.dir, ": ", ec.message()));
    const std::string name = it->path().filename().string();
    if (name.size() <= prefix.size() + suffix.size()) continue;
    if (name.compare(0, prefix.size(), prefix) != 0) continue;
    if (name.compare(name.size() - suffix.size(), suffix.size(), suffix) != 0) continue;
    std::string digits = name.substr(prefix.size(), name.size() - prefix.size() - suffix.size());
    int letter = -1;
    if (lettered) {
      if (digits.size() < 2) continue;
      const char c = digits.back();
      if (c >= 'a' && c <= 'z') {
        letter = c - 'a';
      } else if (c >= 'A' && c <= 'Z') {
        letter = c - 'A';
      } else {
        continue;
      }
      digits.pop_back();
    }
    if (!std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; })) {
      continue;
    }
    const auto first = digits.find_first_not_of('0');
    const std::string significant = first == std::string::npos ? "0" : digits.substr(first);
    if (significant.size() > 9) {
      throw ConfigError(cat(source.dir, "/", name, ": slice number ", digits, " is too large"));
    }
    std::error_code type_ec;
    if (it->is_directory(type_ec)) continue;
    files.push_back({std::stoi(significant), (fs::path(source.dir) / name).string(), letter});
  }
  if (files.empty()) {
    throw ConfigError(cat("no file in ", source.dir, " matches the pattern \"", pattern, "\""));
  }
  std::sort(files.begin(), files.end(), [](const SliceFile& a, const SliceFile& b) {
    if (a.number != b.number) return a.number < b.number;
    return a.letter != b.letter ? a.letter < b.letter : a.path < b.path;
  });
  for (std::size_t i = 1; i < files.size(); ++i) {
    if (files[i].number == files[i - 1].number && files[i].letter == files[i - 1].letter) {
      throw ConfigError(cat("slice number ", files[i].number,
                            files[i].letter >= 0 ? std::string(1, char('a' + files[i].letter)) : "",
                            " appears twice in ", source.dir, ": ",
                            fs::path(files[i - 1].path).filename().string(), " and ",
                            fs::path(files[i].path).filename().string()));
    }
  }
  return files;
}

}  // namespace vispack::pipeline

// Replays a fuzz target over files without libFuzzer, so ctest catches regressions in any build.
// Usage: <target>_replay [--seeds DIR] [FILE|DIR ...]
//   --seeds DIR  writes the target's seed corpus into DIR (created) and replays it.
// Every file is fed to LLVMFuzzerTestOneInput; a crash or sanitizer report fails the run.
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "fuzz_target.h"

namespace fs = std::filesystem;

int main(int argc, char** argv) {
  std::vector<fs::path> inputs;
  for (int i = 1; i < argc; ++i) {
    std::string arg = argv[i];
    if (arg == "--seeds" && i + 1 < argc) {
      fs::path dir = argv[++i];
      fs::create_directories(dir);
      vispack_fuzz_write_seeds(dir.string());
      inputs.push_back(dir);
    } else if (arg == "--help") {
      std::printf("usage: %s [--seeds DIR] [FILE|DIR ...]\n", argv[0]);
      return 0;
    } else {
      inputs.emplace_back(arg);
    }
  }
  std::vector<fs::path> files;
  for (const auto& input : inputs) {
    if (fs::is_directory(input)) {
      for (const auto& entry : fs::recursive_directory_iterator(input))
        if (entry.is_regular_file()) files.push_back(entry.path());
    } else {
      files.push_back(input);
    }
  }
  std::sort(files.begin(), files.end());
  if (files.empty()) {
    std::fprintf(stderr, "replay: no input files\n");
    return 1;
  }
  for (const auto& file : files) {
    std::ifstream in(file, std::ios::binary);
    std::vector<char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    LLVMFuzzerTestOneInput(reinterpret_cast<const std::uint8_t*>(bytes.data()), bytes.size());
  }
  std::printf("replay: %zu inputs ran without a crash\n", files.size());
  return 0;
}

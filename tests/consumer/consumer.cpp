// consumer FILE: opens a packed volume with the installed reader library, reads level 0 of the
// first channel, checks every brick and prints one line:
//   "consumer: <nx> x <ny> x <nz>, <channels> channels, <levels> levels, <bytes> bytes read, ok"
// Exit 0 when the file is sound, 4 when check() finds a defect, 1 on any error.
#include <cstdio>
#include <exception>

#include "vispack/format/reader.h"
#include "vispack/format/summary.h"

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: consumer FILE\n");
    return 2;
  }
  try {
    const auto reader = vispack::format::Reader::open(argv[1]);
    const auto level0 = reader.read_level(0, 0);
    const auto summary = vispack::format::summarize(reader, {true, true, 0});
    const auto d = reader.dims(0);
    std::printf("consumer: %lld x %lld x %lld, %zu channels, %d levels, %zu bytes read, %s\n",
                (long long)d[0], (long long)d[1], (long long)d[2], reader.channels().size(),
                reader.level_count(), level0.size(), summary.findings.empty() ? "ok" : "defect");
    return summary.findings.empty() ? 0 : 4;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "consumer: error: %s\n", e.what());
    return 1;
  }
}

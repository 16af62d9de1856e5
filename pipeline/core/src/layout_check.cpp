// Planar against interleaved from neighbouring samples (layout_check.h).
#include "vispack/pipeline/core/layout_check.h"

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <system_error>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"

namespace vispack::pipeline {

RawLayoutEvidence guess_raw_layout(const std::string& samples) {
  RawLayoutEvidence e;
  const std::size_t n = samples.size();
  if (n < 64) return e;
  const auto* s = reinterpret_cast<const unsigned char*>(samples.data());
  std::uint64_t sum[3] = {0, 0, 0}, count[3] = {0, 0, 0};
  for (std::size_t i = 0; i + 1 < n; ++i) {
    sum[i % 3] += std::uint64_t(std::abs(int(s[i + 1]) - int(s[i])));
    ++count[i % 3];
  }
  double lo = 1e300, hi = 0;
  for (int p = 0; p < 3; ++p) {
    e.phase_mean[p] = double(sum[p]) / double(count[p]);
    lo = std::min(lo, e.phase_mean[p]);
    hi = std::max(hi, e.phase_mean[p]);
  }
  if (hi < 0.5) return e;  // flat: no evidence
  if (hi <= kPlanarSpread * lo) {
    e.guess = RawLayoutGuess::kPlanar;
  } else if (hi > kInterleavedSpread * lo) {
    e.guess = RawLayoutGuess::kInterleaved;
  }
  return e;
}

void check_raw_layout(const SliceSource& source, const std::string& key, const std::string& path,
                      const std::string& config_path) {
  if (!source.raw || source.raw->channels != 3 || source.raw->bits != 8) return;
  const RawLayout& raw = *source.raw;
  const std::uint64_t bytes = std::uint64_t(raw.width) * std::uint64_t(raw.height) * 3;
  std::error_code ec;
  const std::uintmax_t size = std::filesystem::file_size(path, ec);
  if (ec || size != raw.header_bytes + bytes) return;  // the slice reader names a wrong size
  const std::string file = read_file(path, std::size_t(size));
  const RawLayoutEvidence e = guess_raw_layout(file.substr(std::size_t(raw.header_bytes)));
  const bool planar = e.guess == RawLayoutGuess::kPlanar;
  if (e.guess == RawLayoutGuess::kUnknown || planar == raw.planar) return;
  throw ConfigError(cat(config_path, ": ", key, ": \"", raw.planar ? "planar" : "interleaved",
                        "\" reads ", path,
                        " as a scrambled picture: its neighbouring samples differ by ",
                        e.phase_mean[0], ", ", e.phase_mean[1], " and ", e.phase_mean[2],
                        " on average at positions 0, 1 and 2 modulo 3, as in ",
                        planar ? "a planar" : "an interleaved", " file; set ", key, " to \"",
                        planar ? "planar" : "interleaved", "\""));
}

}  // namespace vispack::pipeline

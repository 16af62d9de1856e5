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

namespace {

// Mean |horizontal| and |vertical| neighbour differences of channel 0 of `samples` read as
// width x height (8-bit, `channels` per pixel, planar or interleaved); v / h, or 0 when flat.
double vertical_over_horizontal(const std::string& samples, int width, int height, int channels,
                                bool planar) {
  const auto* s = reinterpret_cast<const unsigned char*>(samples.data());
  const std::size_t step = planar ? 1 : std::size_t(channels);
  auto at = [&](int x, int y) { return int(s[(std::size_t(y) * width + x) * step]); };
  std::uint64_t h = 0, v = 0;
  for (int y = 0; y + 1 < height; ++y)
    for (int x = 0; x + 1 < width; ++x) {
      h += std::uint64_t(std::abs(at(x + 1, y) - at(x, y)));
      v += std::uint64_t(std::abs(at(x, y + 1) - at(x, y)));
    }
  return h == 0 ? 0.0 : double(v) / double(h);
}

}  // namespace

void check_raw_size(const SliceSource& source, const std::string& key_prefix,
                    const std::string& path, const std::string& config_path) {
  if (!source.raw || source.raw->bits != 8 || source.raw->width == source.raw->height) return;
  const RawLayout& raw = *source.raw;
  const std::uint64_t bytes =
      std::uint64_t(raw.width) * std::uint64_t(raw.height) * std::uint64_t(raw.channels);
  std::error_code ec;
  const std::uintmax_t size = std::filesystem::file_size(path, ec);
  if (ec || size != raw.header_bytes + bytes || raw.width < 2 || raw.height < 2) return;
  const std::string samples =
      read_file(path, std::size_t(size)).substr(std::size_t(raw.header_bytes));
  const double as_configured =
      vertical_over_horizontal(samples, raw.width, raw.height, raw.channels, raw.planar);
  const double swapped =
      vertical_over_horizontal(samples, raw.height, raw.width, raw.channels, raw.planar);
  if (as_configured > kSwappedRatio && swapped > 0 && swapped < kUnswappedRatio)
    throw ConfigError(cat(config_path, ": ", key_prefix, ".width, ", key_prefix, ".height: ", path,
                          " read as ", raw.width, "x", raw.height, " has vertical neighbours ",
                          as_configured, "x as different as horizontal ones, read as ", raw.height,
                          "x", raw.width, " ", swapped, "x: width and height look swapped; set ",
                          key_prefix, ".width to ", raw.height, " and ", key_prefix, ".height to ",
                          raw.width));
}

}  // namespace vispack::pipeline

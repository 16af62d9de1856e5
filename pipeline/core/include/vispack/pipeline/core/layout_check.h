// Cheap checks that catch a plausible config mistake before it becomes a silently wrong volume
// (docs/ARCHITECTURE.md, 'Each input at its own z'): a planar raw colour file read as interleaved
// (or the reverse), and a stack whose colour slices are all black.
//
// Raw layout. In an interleaved 8-bit RGB file, of three neighbouring-sample differences
// |s[i+1] − s[i]| two lie inside a pixel (R to G, G to B) and one crosses to the next pixel (B to
// R): their means, taken by the sample's position modulo 3, differ (a blue gel: |G − R| ~ 30,
// |B − G| ~ 140; a grey picture: 0, 0 and the neighbour difference). In a planar file every
// difference is between neighbouring pixels of one channel: the three means agree. So: the three
// phase means within a factor kPlanarSpread say planar, beyond kInterleavedSpread interleaved,
// anything between (or a flat file) nothing. Pure, thread-safe.
#pragma once

#include <string>

#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline {

inline constexpr double kPlanarSpread = 1.25;
inline constexpr double kInterleavedSpread = 2.0;

// What the samples of a raw 8-bit, 3-channel slice say about its layout.
enum class RawLayoutGuess { kUnknown, kPlanar, kInterleaved };
struct RawLayoutEvidence {
  double phase_mean[3] = {0, 0, 0};  // mean |s[i+1] − s[i]| over the i with i mod 3 = 0, 1, 2
  RawLayoutGuess guess = RawLayoutGuess::kUnknown;
};
// `samples`: the file's bytes after its header (width · height · 3 of them).
RawLayoutEvidence guess_raw_layout(const std::string& samples);

// Reads `path` (a slice of `source`, whose raw layout is 8-bit, 3 channels) and throws ConfigError
// (exit 5) naming `key` ("rgb.raw.layout") when its samples say the other layout than the one
// configured; does nothing for other raw layouts or when the samples say nothing.
void check_raw_layout(const SliceSource& source, const std::string& key, const std::string& path,
                      const std::string& config_path);

// Width and height swapped: a slice read with the wrong row length keeps its horizontal
// neighbours (mostly) but its vertical ones lie a row and (width − height) pixels apart. Over the
// first channel of an 8-bit raw slice, v / h (mean |vertical| over mean |horizontal| neighbour
// difference) above kSwappedRatio as configured and under kUnswappedRatio with width and height
// exchanged says swapped (tiny phantom: 9.0 against 1.2). Throws ConfigError naming `key_prefix`
// ("rgb.raw") .width and .height; does nothing for a square slice, another bit depth, a file of
// another size, or a flat picture.
inline constexpr double kSwappedRatio = 3.0;
inline constexpr double kUnswappedRatio = 1.5;
void check_raw_size(const SliceSource& source, const std::string& key_prefix,
                    const std::string& path, const std::string& config_path);

}  // namespace vispack::pipeline

// The z of every input slice and the pairings along z (slice_z.h; docs/ARCHITECTURE.md, 'Each input
// at its own z').
#include "vispack/pipeline/core/slice_z.h"

#include <algorithm>
#include <cmath>

#include "vispack/common/error.h"

namespace vispack::pipeline {
namespace {

// Positions within this fraction of a slice spacing of a slice count as on it.
constexpr double kOnSlice = 1e-6;

// A length in mm for a message: two decimals at most, trailing zeros dropped.
double mm(double value) {
  return std::round(value * 100.0) / 100.0;
}

}  // namespace

double colour_z_mm(const Config& config, int colour_k) {
  return colour_k * config.spacing_mm[2];
}

double ct_slice_spacing_mm(const Config& config) {
  return config.ct ? config.ct->slice_spacing_mm.value_or(config.spacing_mm[2]) : 0.0;
}

CtAtZ ct_at_colour_slice(const Config& config, int ct_count, int colour_k) {
  CtAtZ at;
  if (!config.ct || ct_count <= 0) return at;
  const double spacing = ct_slice_spacing_mm(config);
  // Position in CT slices: CT slice j lies at position j.
  const double p = (colour_z_mm(config, colour_k) - config.ct->z_offset_mm) / spacing;
  if (p < -kOnSlice || p > ct_count - 1 + kOnSlice) return at;
  const double nearest = std::round(p);
  if (std::abs(p - nearest) <= kOnSlice) {
    at.below = at.above = std::clamp(int(nearest), 0, ct_count - 1);
    return at;
  }
  at.below = int(std::floor(p));
  at.above = at.below + 1;
  at.w_above = p - at.below;
  at.distance_mm = std::min(at.w_above, 1.0 - at.w_above) * spacing;
  return at;
}

int seg_at_colour_slice(const Config& config, int seg_count, int colour_k) {
  if (!config.seg || !config.seg->slice_spacing_mm || seg_count <= 0) return -1;
  const double spacing = *config.seg->slice_spacing_mm;
  const double p = (colour_z_mm(config, colour_k) - config.seg->z_offset_mm) / spacing;
  const double nearest = std::round(p);
  // Half a spacing from the nearest slice, or beyond the stack's ends by more than that: none.
  if (nearest < 0 || nearest > seg_count - 1) return -1;
  if (std::abs(p - nearest) > 0.5 + kOnSlice) return -1;
  return int(nearest);
}

int colour_slice_of_seg(const Config& config, int colour_count, int seg_j) {
  if (!config.seg || !config.seg->slice_spacing_mm) return std::clamp(seg_j, 0, colour_count - 1);
  const double z = config.seg->z_offset_mm + seg_j * *config.seg->slice_spacing_mm;
  const double k = std::round(z / config.spacing_mm[2]);
  return int(std::clamp(k, 0.0, double(colour_count - 1)));
}

std::string check_z_extent(const Config& config, const std::string& input, int colour_count,
                           int input_count, double input_spacing_mm, double input_z_offset_mm) {
  const double colour_spacing = config.spacing_mm[2];
  const double colour_extent = (colour_count - 1) * colour_spacing;
  const double input_extent = (input_count - 1) * input_spacing_mm;
  const double lo = std::max(0.0, input_z_offset_mm);
  const double hi = std::min(colour_extent, input_z_offset_mm + input_extent);
  const double overlap = std::max(0.0, hi - lo);
  const std::string figures =
      cat(input, ": ", input_count, " slices x ", input_spacing_mm, " mm cover ", mm(input_extent),
          " mm", input_z_offset_mm != 0 ? cat(" from z ", mm(input_z_offset_mm), " mm") : "",
          " of the colour stack's ", mm(colour_extent), " mm (", colour_count, " slices x ",
          colour_spacing, " mm)");
  if (colour_count > 1 && overlap < 0.5 * colour_extent - 1e-9) {
    const bool spacing_short = input_extent < 0.5 * colour_extent - 1e-9;
    throw ConfigError(cat(config.path, ": ", figures, "; set ", input,
                          spacing_short ? ".slice_spacing_mm" : ".z_offset_mm"));
  }
  if (std::abs(input_extent - colour_extent) > 2 * input_spacing_mm + 1e-9)
    return cat(figures, ": the extents differ by ", mm(std::abs(input_extent - colour_extent)),
               " mm; check ", input, ".slice_spacing_mm and ", input, ".z_offset_mm");
  return "";
}

std::vector<std::string> check_z_extents(const Config& config, int colour_count, int ct_count,
                                         int seg_count) {
  std::vector<std::string> warnings;
  if (config.ct && ct_count > 0) {
    std::string w = check_z_extent(config, "ct", colour_count, ct_count,
                                   ct_slice_spacing_mm(config), config.ct->z_offset_mm);
    if (!w.empty()) warnings.push_back(std::move(w));
  }
  if (config.seg && config.seg->slice_spacing_mm && seg_count > 0) {
    std::string w = check_z_extent(config, "seg", colour_count, seg_count,
                                   *config.seg->slice_spacing_mm, config.seg->z_offset_mm);
    if (!w.empty()) warnings.push_back(std::move(w));
  }
  return warnings;
}

}  // namespace vispack::pipeline

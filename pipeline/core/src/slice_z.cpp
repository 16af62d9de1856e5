// The z of every input slice and the pairings along z (slice_z.h; docs/ARCHITECTURE.md, 'Each input
// at its own z').
#include "vispack/pipeline/core/slice_z.h"

#include <algorithm>
#include <cmath>
#include <filesystem>

#include "vispack/common/error.h"

namespace vispack::pipeline {
namespace {

// Positions within this fraction of a slice spacing of a slice count as on it.
constexpr double kOnSlice = 1e-6;

// A length in mm for a message: two decimals at most, trailing zeros dropped.
double mm(double value) {
  return std::round(value * 100.0) / 100.0;
}

std::string file_name(const SliceFile& f) {
  return std::filesystem::path(f.path).filename().string();
}

// With {n}{a}: the colour slices per file number (numbers count millimetres, slice_z.h).
int letters_per_number(const Config& config) {
  const double per_mm = 1.0 / config.spacing_mm[2];
  const double letters = std::round(per_mm);
  if (letters < 1 || letters > 26 || std::abs(per_mm - letters) > 1e-6 * letters)
    throw ConfigError(cat(config.path, ": spacing_mm[2]: ", config.spacing_mm[2],
                          " mm does not divide a millimetre into 1 to 26 slices, as the lettered "
                          "pattern rgb.pattern \"",
                          config.rgb.pattern,
                          "\" needs (its numbers count millimetres, its letters the slices "
                          "within one; e.g. 0.3333333333333333 for a, b, c)"));
  return int(letters);
}

// The smallest difference between consecutive numbers (1 for a stack of one).
int number_step(const std::vector<SliceFile>& files) {
  int step = 0;
  for (std::size_t i = 1; i < files.size(); ++i) {
    const int d = files[i].number - files[i - 1].number;
    if (d > 0 && (step == 0 || d < step)) step = d;
  }
  return step > 0 ? step : 1;
}

bool lettered(const std::vector<SliceFile>& files) {
  return !files.empty() && files.front().letter >= 0;
}

}  // namespace

void place_colour_slices(const Config& config, std::vector<SliceFile>& colour) {
  if (colour.empty()) return;
  const SliceFile first = colour.front();
  if (lettered(colour)) {
    const int letters = letters_per_number(config);
    for (auto& f : colour) {
      if (f.letter >= letters)
        throw InputError(cat(f.path, ": letter '", char('a' + f.letter), "' is beyond the ",
                             letters, " slices per millimetre that spacing_mm[2] (",
                             config.spacing_mm[2], " mm) allows (a to ", char('a' + letters - 1),
                             "); the file's place along z is undefined"));
      f.slot = (f.number - first.number) * letters + f.letter - first.letter;
    }
    return;
  }
  const int step = number_step(colour);
  for (auto& f : colour) {
    if ((f.number - first.number) % step != 0)
      throw InputError(cat(f.path, ": number ", f.number, " is not a whole number of steps (", step,
                           ", the smallest difference between numbers) from the first, ",
                           file_name(first), "; the file's place along z is undefined"));
    f.slot = (f.number - first.number) / step;
  }
}

std::vector<MissingColourSlice> missing_colour_slices(const Config& config,
                                                      const std::vector<SliceFile>& colour) {
  std::vector<MissingColourSlice> missing;
  if (colour.empty()) return missing;
  const SliceFile& first = colour.front();
  const bool letters = lettered(colour);
  const int per_number = letters ? letters_per_number(config) : 1;
  const int step = letters ? 1 : number_step(colour);
  for (std::size_t i = 1; i < colour.size() && missing.size() < 100000; ++i)
    for (int slot = colour[i - 1].slot + 1; slot < colour[i].slot && missing.size() < 100000;
         ++slot) {
      // Slot back to number (and letter), relative to the first file.
      const int from_first = slot + (letters ? first.letter : 0);
      const int number = first.number + (from_first / per_number) * step;
      missing.push_back(
          {slot, letters ? cat(number, char('a' + from_first % per_number)) : cat(number)});
    }
  return missing;
}

int colour_slot_count(const std::vector<SliceFile>& colour) {
  return colour.empty() ? 0 : colour.back().slot + 1;
}

int colour_slot_of_stack_index(const std::vector<SliceFile>& colour, int colour_k) {
  return colour_k < int(colour.size()) ? colour[std::size_t(colour_k)].slot
                                       : colour_slot_count(colour);
}

SliceRange colour_slots_of_stack_range(const std::vector<SliceFile>& colour, SliceRange stack) {
  return {colour_slot_of_stack_index(colour, stack.first),
          colour_slot_of_stack_index(colour, stack.last)};
}

SliceRange stack_range_of_colour_slots(const std::vector<SliceFile>& colour, SliceRange slots) {
  auto first_at = [&](int slot) {
    return int(std::lower_bound(colour.begin(), colour.end(), slot,
                                [](const SliceFile& f, int s) { return f.slot < s; }) -
               colour.begin());
  };
  return {first_at(slots.first), first_at(slots.last)};
}

double colour_z_mm(const Config& config, int colour_slot) {
  return colour_slot * config.spacing_mm[2];
}

double ct_slice_spacing_mm(const Config& config) {
  return config.ct ? config.ct->slice_spacing_mm.value_or(config.spacing_mm[2]) : 0.0;
}

CtAtZ ct_at_colour_slice(const Config& config, int ct_count, int colour_slot) {
  CtAtZ at;
  if (!config.ct || ct_count <= 0) return at;
  const double spacing = ct_slice_spacing_mm(config);
  // Position in CT slices: CT slice j lies at position j.
  const double p = (colour_z_mm(config, colour_slot) - config.ct->z_offset_mm) / spacing;
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

int seg_at_colour_slice(const Config& config, int seg_count, int colour_slot) {
  if (!config.seg || !config.seg->slice_spacing_mm || seg_count <= 0) return -1;
  const double spacing = *config.seg->slice_spacing_mm;
  const double p = (colour_z_mm(config, colour_slot) - config.seg->z_offset_mm) / spacing;
  const double nearest = std::round(p);
  // Half a spacing from the nearest slice, or beyond the stack's ends by more than that: none.
  if (nearest < 0 || nearest > seg_count - 1) return -1;
  if (std::abs(p - nearest) > 0.5 + kOnSlice) return -1;
  return int(nearest);
}

int colour_slice_of_seg(const Config& config, const std::vector<SliceFile>& colour, int seg_j) {
  const int colour_count = int(colour.size());
  if (!config.seg || !config.seg->slice_spacing_mm) return std::clamp(seg_j, 0, colour_count - 1);
  const double z = config.seg->z_offset_mm + seg_j * *config.seg->slice_spacing_mm;
  const double slot = z / config.spacing_mm[2];
  // The first placed slice at or after `slot`, or the one before it, whichever lies nearer.
  auto it = std::lower_bound(colour.begin(), colour.end(), slot,
                             [](const SliceFile& f, double s) { return f.slot < s; });
  if (it == colour.end()) return colour_count - 1;
  if (it == colour.begin()) return 0;
  const auto before = it - 1;
  // Without gaps this is std::round(slot): a tie goes to the later slice.
  return int((slot - before->slot < it->slot - slot ? before : it) - colour.begin());
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

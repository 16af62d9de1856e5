// Where each input slice lies along z (docs/ARCHITECTURE.md, 'Each input at its own z'): colour, CT
// and segmentation each have their own slice spacing and z offset, and every pairing of a CT or
// segmentation slice with a colour slice goes through this file, never through equal stack indices.
//
// Frames and units. z is in mm along the stack, 0 at the colour stack's first file:
//   z of colour slice k (stack index k; output z = slot_k)  = slot_k · spacing_mm[2]
//   z of CT slice j (the CT stack index, sorted by number)  = ct.z_offset_mm + j ·
//   ct.slice_spacing_mm z of segmentation slice j (with seg.slice_spacing_mm)   = seg.z_offset_mm +
//   j · seg.slice_spacing_mm
// The colour slot comes from the file's number, never from its position in the stack
// (place_colour_slices): a colour file missing inside the stack leaves its slot empty and every
// later slice keeps its z against the CT and the segmentation, and the packed volume has an empty
// slice at that z (its depth is colour_slot_count). Without gaps slot_k = k.
// Variables name their stack: `colour_k` for a colour slice index, `colour_slot` for its slot,
// `ct_j` / `seg_j` for an index into the CT / segmentation stack. Defaults (ct.slice_spacing_mm =
// spacing_mm[2], z_offset_mm = 0) put CT slice j exactly on colour slot j: the 1:1 case reads one
// CT slice per colour slice, with no interpolation, exactly as before the keys existed.
//
// The slot rule (docs/ARCHITECTURE.md "Each input at its own z"):
// - pattern {n}: the step is the smallest difference between consecutive numbers (1 for rgb_0000,
//   rgb_0001, ...; 3 for rgb_0000, rgb_0003, ...); slot = (number − first number) / step. A number
//   that is not a whole number of steps from the first is an InputError naming the file.
// - pattern {n}{a}: numbers count millimetres (NLM's female: avf1001a, b, c span 1 mm) and the
//   letters the slices within one: letters per number L = 1 mm / spacing_mm[2] (3 at 1/3 mm), a
//   whole number 1..26 (else a ConfigError naming spacing_mm[2] and rgb.pattern); slot =
//   (number − first number) · L + letter − first letter. A letter at or beyond L ('d' at 1/3 mm)
//   is an InputError naming the file.
//
// What the pipeline does with it (docs/ARCHITECTURE.md "Each input at its own z"):
// - the CT of a colour slice is the CT interpolated linearly in HU between the two CT slices
//   around its z (the body mask, the packed ct channel and the register stage's anchor);
// - a colour slice whose z lies outside the CT's z range (beyond half a micrometre) gets no CT:
//   no anchor, a colour-only mask, CT −1024 HU (air) in the packed channel;
// - the labels of a colour slice come from the segmentation slice nearest in z (never blended);
//   none within half a segmentation spacing: label 0, listed in the labels report.
// Everything here is pure and thread-safe.
#pragma once

#include <string>
#include <vector>

#include "vispack/common/cli.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/slice_list.h"

namespace vispack::pipeline {

// Sets `slot` of every colour file (sorted as list_slices sorts them) by the rule above. Throws
// ConfigError (letters per number not whole) or InputError (a file off the grid of slots).
void place_colour_slices(const Config& config, std::vector<SliceFile>& colour);

// The colour slots that no file fills between the first and the last, each with its name: the
// number for {n} ("1002"), number and letter for {n}{a} ("1002b"). Needs placed slices.
struct MissingColourSlice {
  int slot;
  std::string name;
};
std::vector<MissingColourSlice> missing_colour_slices(const Config& config,
                                                      const std::vector<SliceFile>& colour);

// The number of colour slots the stack spans (last slot + 1; 0 for an empty stack).
int colour_slot_count(const std::vector<SliceFile>& colour);

// The slot (output z) where stack slice `colour_k` begins: colour[colour_k].slot, and
// colour_slot_count for colour_k == colour.size(). A range [A, B) of stack indices (a --slices
// shard) covers the slots [slot of A, slot of B): the empty slots after its last file are its own,
// so ranges that tile the stack tile the slots (colour_slots_of_stack_range). Needs placed slices.
int colour_slot_of_stack_index(const std::vector<SliceFile>& colour, int colour_k);
SliceRange colour_slots_of_stack_range(const std::vector<SliceFile>& colour, SliceRange stack);
// The inverse: the stack indices [A, B) whose files lie in the slots [first, last) (A: the first
// file at or after slot `first`, B: the first at or after `last`), for messages that name the
// --slices shard holding some slots.
SliceRange stack_range_of_colour_slots(const std::vector<SliceFile>& colour, SliceRange slots);

// z (mm) of colour slot `colour_slot` (slot_k of colour slice k).
double colour_z_mm(const Config& config, int colour_slot);
// ct.slice_spacing_mm as configured, spacing_mm[2] when unset; 0 without CT.
double ct_slice_spacing_mm(const Config& config);

// The CT at one colour slot's z (pass files[k].slot for colour slice k): CT slices `below` and
// `above` (CT stack indices) weighted linearly, hu = (1 − w_above) · hu[below] + w_above ·
// hu[above]. A colour slice that lies on a CT slice (within 1e-6 of a CT spacing) has below ==
// above and w_above == 0; one outside the CT's z range has below == above == −1.
struct CtAtZ {
  int below = -1;
  int above = -1;
  double w_above = 0.0;
  bool inside() const { return below >= 0; }
  bool exact() const { return below >= 0 && below == above; }
  int nearest() const { return w_above > 0.5 ? above : below; }
  // z distance (mm) from the colour slice to the nearest CT slice; 0 when exact or outside.
  double distance_mm = 0.0;
};
CtAtZ ct_at_colour_slice(const Config& config, int ct_count, int colour_slot);

// The segmentation slice (stack index into the segmentation stack) nearest the z of colour slot
// `colour_slot`, or −1 when none lies within half a segmentation spacing (seg.slice_spacing_mm must
// be set: without it segmentation slices are matched to colour slices by file number, labels.h).
int seg_at_colour_slice(const Config& config, int seg_count, int colour_slot);

// The colour slice (stack index) nearest the z of segmentation slice `seg_j` among the placed
// colour files (the first or last one beyond the stack's ends): the slice whose observed (drifted)
// grid the segmentation was drawn on, whose transform carries it to the output grid.
int colour_slice_of_seg(const Config& config, const std::vector<SliceFile>& colour, int seg_j);

// The extents check of one input ("ct" or "seg") against the colour stack: z extents are from
// the first slice to the last, (count − 1) · spacing; `colour_count` counts colour slots
// (colour_slot_count: with a gap, the slots the stack spans). When the input's z range covers less
// than half of the colour stack's z extent, a ConfigError (exit 5) of one line naming both counts,
// spacings and extents and the key to set (`ct.slice_spacing_mm`, or `ct.z_offset_mm` when the
// extent would do but the offset puts it beside the stack). When the extents differ by more than
// two of the input's slices, returns a warning with the same figures (a CT may legitimately reach
// beyond the colour stack); else an empty string.
std::string check_z_extent(const Config& config, const std::string& input, int colour_count,
                           int input_count, double input_spacing_mm, double input_z_offset_mm);

// Both checks for the config's CT and segmentation (with seg.slice_spacing_mm set): the warnings,
// in that order. Throws as check_z_extent does.
std::vector<std::string> check_z_extents(const Config& config, int colour_count, int ct_count,
                                         int seg_count);

}  // namespace vispack::pipeline

// Where each input slice lies along z (docs/ARCHITECTURE.md, 'Each input at its own z'): colour, CT
// and segmentation each have their own slice spacing and z offset, and every pairing of a CT or
// segmentation slice with a colour slice goes through this file, never through equal stack indices.
//
// Frames and units. z is in mm along the stack, 0 at colour slice 0:
//   z of colour slice k (the stack index, = output z)   = k · spacing_mm[2]
//   z of CT slice j (the CT stack index, sorted by number) = ct.z_offset_mm + j ·
//   ct.slice_spacing_mm z of segmentation slice j (with seg.slice_spacing_mm)  = seg.z_offset_mm +
//   j · seg.slice_spacing_mm
// Variables name their stack: `colour_k` for a colour slice index, `ct_j` / `seg_j` for an index
// into the CT / segmentation stack. Defaults (ct.slice_spacing_mm = spacing_mm[2], z_offset_mm =
// 0) put CT slice k exactly on colour slice k: the 1:1 case reads one CT slice per colour slice,
// with no interpolation, exactly as before the keys existed.
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

#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline {

// z (mm) of colour slice `colour_k`.
double colour_z_mm(const Config& config, int colour_k);
// ct.slice_spacing_mm as configured, spacing_mm[2] when unset; 0 without CT.
double ct_slice_spacing_mm(const Config& config);

// The CT at one colour slice's z: CT slices `below` and `above` (CT stack indices) weighted
// linearly, hu = (1 − w_above) · hu[below] + w_above · hu[above]. A colour slice that lies on a
// CT slice (within 1e-6 of a CT spacing) has below == above and w_above == 0; one outside the CT's
// z range has below == above == −1.
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
CtAtZ ct_at_colour_slice(const Config& config, int ct_count, int colour_k);

// The segmentation slice (stack index into the segmentation stack) nearest the z of colour slice
// `colour_k`, or −1 when none lies within half a segmentation spacing (seg.slice_spacing_mm must
// be set: without it segmentation slices are matched to colour slices by file number, labels.h).
int seg_at_colour_slice(const Config& config, int seg_count, int colour_k);

// The colour slice nearest the z of segmentation slice `seg_j`, clamped to [0, colour_count): the
// slice whose observed (drifted) grid the segmentation was drawn on, whose transform carries it to
// the output grid.
int colour_slice_of_seg(const Config& config, int colour_count, int seg_j);

// The extents check of one input ("ct" or "seg") against the colour stack: z extents are from
// the first slice to the last, (count − 1) · spacing. When the input's z range covers less than
// half of the colour stack's z extent, a ConfigError (exit 5) of one line naming both counts,
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

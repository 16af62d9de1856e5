// The work folder: where each stage's intermediates live (docs/ARCHITECTURE.md "Work folder
// layout"), the stack's slice list and transforms. Reading the intermediates back (pack, vdb):
// imaging/intermediates.h.
// All functions are thread-safe (they only read the config and the file system).
#pragma once

#include <string>
#include <vector>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/fingerprint.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/core/transform_types.h"

namespace vispack::pipeline {

// Paths in the work folder (all absolute; no folder is created).
std::string stage_dir(const Config& config, const std::string& stage);  // <work>/<stage>
// <work>/<stage>/<prefix>_NNNN.<ext>, NNNN = stack index k (zero-padded to 4 digits, more if
// needed), e.g. slice_output_path(config, "mask", "mask", 7) = <work>/mask/mask_0007.png.
std::string slice_output_path(const Config& config, const std::string& stage,
                              const std::string& prefix, int index, const std::string& ext = "png");
// <work>/register/transforms.json
std::string transforms_path(const Config& config);
// <work>/register/registered/rgb_NNNN.png (the registered colour slice k; written only with
// work.write_registered, for inspection: no stage reads it back)
std::string registered_rgb_path(const Config& config, int index);
// <work>/mask/mask_NNNN.png (0/255), <work>/mask/ct_NNNN.png (16-bit, HU + 32768; written only
// with work.write_ct, for inspection),
// <work>/labels/labels_NNNN.png (16-bit IDs)
std::string mask_path(const Config& config, int index);
std::string mask_ct_path(const Config& config, int index);
std::string labels_path(const Config& config, int index);

// The colour stack: list_slices(config.rgb), each file placed along z by its number
// (slice_z.h place_colour_slices: SliceFile::slot). Its order defines the stack index k (= output
// z). Throws what place_colour_slices throws (a letter beyond the spacing: InputError).
// Throws InputError when a CT slice is missing inside the CT stack, ConfigError when the CT or
// the segmentation covers less than half the colour stack's z extent (z_extent_warnings).
std::vector<SliceFile> stack_slices(const Config& config);

// Slices placed along z by their position in their stack (CT; segmentation with
// seg.slice_spacing_mm) must not miss one inside the stack: that would shift every later one.
// The step is the smallest difference between consecutive numbers (1 for ct_0000, ct_0001, ...;
// 3 for ct_0000, ct_0003, ...). Throws InputError naming the folder, the missing number and its
// neighbours; `what` names the stack ("CT").
void check_no_missing_slice(const SliceSource& source, const std::vector<SliceFile>& files,
                            const std::string& what);

// The z extent checks of slice_z.h check_z_extents for the config's CT and segmentation folders
// against a colour stack spanning `colour_count` slots (colour_slot_count): the warnings (extents
// that differ by more than two of the input's slices); throws ConfigError (exit 5) naming the key
// when an input covers less than half of the colour stack.
std::vector<std::string> z_extent_warnings(const Config& config, int colour_count);

// A gap in the colour stack (slice_z.h missing_colour_slices: a number missing; with {n}{a}, a
// letter): every colour slice keeps its z from its file number, so the CT and the segmentation
// stay paired right, but the packed volume has an empty slice there. The warning names the first
// missing slice and its neighbours and how many more there are; "" when none is missing. Needs a
// placed stack (stack_slices).
std::string colour_gap_warning(const Config& config, const std::vector<SliceFile>& colour);

// The register stage's transforms for a stack of `slice_count` slices: reads
// <work>/register/transforms.json. Throws InputError naming the file when it is missing ("run
// vispack-register first") or covers another number of slices ("rerun vispack-register").
StackTransforms read_stack_transforms(const Config& config, int slice_count);

// What the later stages need to rebuild a slice's registered colour and resampled CT from the
// inputs (docs/ARCHITECTURE.md, 'Work folder layout': those full-size images are not written by
// default, config "work").
struct StackInputs {
  std::vector<SliceFile> rgb;  // stack_slices(config): index k = output slice k
  std::vector<SliceFile> ct;   // list_slices(*config.ct), empty without CT
  StackTransforms transforms;  // <work>/register/transforms.json, one per colour slice
};
// Lists the slice folders and reads transforms.json (read_stack_transforms: same errors).
StackInputs read_stack_inputs(const Config& config);

// A fingerprint of everything a whole-volume stage reads (pack, vdb): transforms.json, then per
// slice the input colour slice, the mask, the CT slice (when CT is configured) and the labels
// (when segmentation is configured). Callers add their own inputs and options to it.
Fingerprint intermediates_fingerprint(const Config& config, const StackInputs& inputs);

}  // namespace vispack::pipeline

// The work folder: where each stage's intermediates live (docs/ARCHITECTURE.md "Work folder
// layout"), the stack's slice list, and the one way to read the intermediates back (pack, vdb).
// All functions are thread-safe (they only read the config and the file system).
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/fingerprint.h"
#include "vispack/pipeline/slice_io.h"
#include "vispack/pipeline/transforms.h"

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

// The colour stack: list_slices(config.rgb). Its order defines the stack index k (= output z).
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
// against a colour stack of `colour_count` slices: the warnings (extents that differ by more than
// two of the input's slices); throws ConfigError (exit 5) naming the key when an input covers
// less than half of the colour stack.
std::vector<std::string> z_extent_warnings(const Config& config, int colour_count);

// The register stage's transforms for a stack of `slice_count` slices: reads
// <work>/register/transforms.json. Throws InputError naming the file when it is missing ("run
// vispack-register first") or covers another number of slices ("rerun vispack-register").
StackTransforms read_stack_transforms(const Config& config, int slice_count);

// What the later stages need to rebuild a slice's registered colour and resampled CT from the
// inputs (issue 12: those full-size images are not written by default, config "work").
struct StackInputs {
  std::vector<SliceFile> rgb;  // stack_slices(config): index k = output slice k
  std::vector<SliceFile> ct;   // list_slices(*config.ct), empty without CT
  StackTransforms transforms;  // <work>/register/transforms.json, one per colour slice
  cv::Size size() const { return {transforms.width, transforms.height}; }
};
// Lists the slice folders and reads transforms.json (read_stack_transforms: same errors).
StackInputs read_stack_inputs(const Config& config);

// The registered colour slice k (CV_8UC3, RGB) on the output grid: input slice k (16-bit scaled
// to 8, grey expanded to RGB) resampled with its transform (bilinear, border replicated; the
// convention of docs/ARCHITECTURE.md "Slice transforms"). The one implementation: register
// writes it when work.write_registered, mask, pack and vdb call it. Deterministic: the same
// inputs give the same bytes. Throws InputError naming the slice when its size differs.
cv::Mat registered_colour(const Config& config, const StackInputs& inputs, int index);

// A CT slice file in HU (CV_32F): stored value × ct.slope + ct.intercept. Throws InputError
// naming the file when it is not single-channel.
cv::Mat read_ct_hu(const CtSource& ct, const std::string& path);

// The CT in HU (CV_32F, CT resolution) at the z of colour slice `colour_k` (slice_z.h): the one CT
// slice read as is when the colour slice lies on it (the 1:1 case), else the two CT slices around
// its z blended linearly in HU; empty outside the CT's z range or without CT. `ct_files` is the
// CT stack (list_slices(*config.ct)). Throws InputError naming a file that is not single-channel
// or whose size differs from its neighbour's.
cv::Mat ct_hu_at_colour_slice(const Config& config, const std::vector<SliceFile>& ct_files,
                              int colour_k);

// The CT at output slice k's z in HU (ct_hu_at_colour_slice) and the map from output pixels to
// its pixels (transforms.h output_to_ct with transforms.json's ct_to_rgb, else the config's
// definition). Without CT, or when slice k lies outside the CT's z range, `hu` is empty.
// With `for_mask`, a slice between two CT slices is also checked for `body_ends`.
struct CtSlice {
  cv::Mat hu;
  cv::Matx23d out_to_ct{1, 0, 0, 0, 1, 0};
  std::string path;  // the CT file nearest in z; empty when none
  // The two CT slices around this z do not show one body (ct_body_mask at the mask's edge level:
  // one has none, or they overlap by less than half the smaller): a body's tip, which the blend
  // loses (a third of the way for soft tissue). The mask stage takes the colour alone there.
  bool body_ends = false;
};
CtSlice read_ct_slice(const Config& config, const StackInputs& inputs, int index,
                      bool for_mask = false);

// The CT of output slice k on the output grid as work/mask/ct_NNNN.png stores it (CV_16UC1,
// HU + 32768; mask.h resample_ct, encode_hu16): the one implementation the mask stage writes
// (work.write_ct) and pack and vdb read. A slice beyond the CT stack is −1024 HU (air)
// everywhere. `ct` (optional) is the slice already read.
cv::Mat resampled_ct16(const Config& config, const StackInputs& inputs, int index,
                       const CtSlice* ct = nullptr);

// A fingerprint of everything a whole-volume stage reads (pack, vdb): transforms.json, then per
// slice the input colour slice, the mask, the CT slice (when CT is configured) and the labels
// (when segmentation is configured). Callers add their own inputs and options to it.
Fingerprint intermediates_fingerprint(const Config& config, const StackInputs& inputs);

// One output slice's intermediates, as the mask and labels stages wrote them, on the output grid,
// with what lies outside the body cleared as the config asks (pack.keep_outside_body).
struct Intermediates {
  cv::Mat rgb;              // CV_8UC3, the registered colour slice; (0, 0, 0) where mask == 0
                            // unless config.pack.keep_colour_outside_body
  cv::Mat mask;             // CV_8UC1, 0/255 body mask
  cv::Mat ct;               // CV_16UC1, HU + 32768 (empty without CT); kOutsideBodyCt16 (−1024
                            // HU, air) where mask == 0 unless config.pack.keep_ct_outside_body
  cv::Mat labels;           // CV_16UC1, label IDs (empty without segmentation)
  std::uint64_t bytes = 0;  // decoded bytes of the slices above (for throughput reports)
};

// The CT value stored outside the body when it is cleared: −1024 HU (air) as HU + 32768.
constexpr std::uint16_t kOutsideBodyCt16 = 32768 - 1024;

// The intermediates of stack slice `index` on the output grid (inputs.size()): mask and labels
// read from the work folder, each checked for size and type; colour and CT rebuilt from the
// inputs (registered_colour, resampled_ct16), whether or not the work folder holds copies.
// CT only when the config has CT and labels only when it has segmentation. Outside the
// body mask (mask == 0) colour becomes 0 and CT −1024 HU unless config.pack says to keep them
// (docs/ARCHITECTURE.md "What the packed file stores"): this is the one place where that
// happens, so the packed file and the OpenVDB export read the same values. Throws InputError
// naming the file when one is missing ("run the earlier stages first") or has the wrong size or
// pixel type.
Intermediates read_intermediates(const Config& config, const StackInputs& inputs, int index);

// An intermediate image of the work folder (a mask or label PNG), checked: throws InputError
// naming `path` when it is missing ("run the earlier stages first") or is not of `type`
// (CV_8UC1, CV_8UC3 or CV_16UC1) and `size`.
cv::Mat read_checked(const std::string& path, int type, cv::Size size);

// The clearing step of read_intermediates, for intermediates built in memory (the streaming
// vispack-run, stream.h): colour 0 and CT −1024 HU where in.mask == 0, as config.pack asks.
// `in` must hold rgb and mask (and ct when the config has CT) of one size.
void clear_outside_body(const Config& config, Intermediates& in);

// The union over stack slices [0, slice_count) of the bounding boxes of the body masks
// (<work>/mask/mask_NNNN.png, non-zero pixels), in output-grid pixels; an empty rect when no
// slice has body. Throws InputError as read_intermediates does for a missing or wrong mask.
cv::Rect body_bounds(const Config& config, int slice_count, cv::Size size);

}  // namespace vispack::pipeline

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
// <work>/register/registered/rgb_NNNN.png (the registered colour slice k)
std::string registered_rgb_path(const Config& config, int index);
// <work>/mask/mask_NNNN.png (0/255), <work>/mask/ct_NNNN.png (16-bit, HU + 32768),
// <work>/labels/labels_NNNN.png (16-bit IDs)
std::string mask_path(const Config& config, int index);
std::string mask_ct_path(const Config& config, int index);
std::string labels_path(const Config& config, int index);

// The colour stack: list_slices(config.rgb). Its order defines the stack index k (= output z).
std::vector<SliceFile> stack_slices(const Config& config);

// The register stage's transforms for a stack of `slice_count` slices: reads
// <work>/register/transforms.json. Throws InputError naming the file when it is missing ("run
// vispack-register first") or covers another number of slices ("rerun vispack-register").
StackTransforms read_stack_transforms(const Config& config, int slice_count);

// A fingerprint of every intermediate a whole-volume stage reads (pack, vdb): transforms.json,
// then per slice the registered colour, the mask, the resampled CT (when CT is configured) and the
// labels (when segmentation is configured). Callers add their own inputs and options to it.
Fingerprint intermediates_fingerprint(const Config& config, int slice_count);

// One output slice's intermediates, as the mask and labels stages wrote them, on the output grid.
struct Intermediates {
  cv::Mat rgb;              // CV_8UC3, the registered colour slice
  cv::Mat mask;             // CV_8UC1, 0/255 body mask
  cv::Mat ct;               // CV_16UC1, HU + 32768 (empty without CT)
  cv::Mat labels;           // CV_16UC1, label IDs (empty without segmentation)
  std::uint64_t bytes = 0;  // decoded bytes read (for throughput reports)
};

// Reads the intermediates of stack slice `index`, each checked to be `size` and of its type.
// Reads ct only when the config has CT and labels only when it has segmentation. Throws
// InputError naming the file when one is missing ("run the earlier stages first") or has the
// wrong size or pixel type.
Intermediates read_intermediates(const Config& config, int index, cv::Size size);

}  // namespace vispack::pipeline

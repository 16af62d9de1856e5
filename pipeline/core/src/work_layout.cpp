#include "vispack/pipeline/core/work_layout.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <set>
#include <string>

#include "vispack/common/error.h"
#include "vispack/pipeline/core/slice_z.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

namespace {

std::string padded(int index) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%04d", index);
  return buffer;
}

}  // namespace

std::string stage_dir(const Config& config, const std::string& stage) {
  return config.work_dir + "/" + stage;
}

std::string slice_output_path(const Config& config, const std::string& stage,
                              const std::string& prefix, int index, const std::string& ext) {
  return stage_dir(config, stage) + "/" + prefix + "_" + padded(index) + "." + ext;
}

std::string transforms_path(const Config& config) {
  return stage_dir(config, "register") + "/transforms.json";
}

std::string registered_rgb_path(const Config& config, int index) {
  return stage_dir(config, "register") + "/registered/rgb_" + padded(index) + ".png";
}

std::string mask_path(const Config& config, int index) {
  return slice_output_path(config, "mask", "mask", index);
}

std::string mask_ct_path(const Config& config, int index) {
  return slice_output_path(config, "mask", "ct", index);
}

std::string labels_path(const Config& config, int index) {
  return slice_output_path(config, "labels", "labels", index);
}

void check_no_missing_slice(const SliceSource& source, const std::vector<SliceFile>& files,
                            const std::string& what) {
  int step = 0;
  for (std::size_t i = 1; i < files.size(); ++i) {
    const int d = files[i].number - files[i - 1].number;
    if (step == 0 || d < step) step = d;
  }
  for (std::size_t i = 1; i < files.size(); ++i) {
    if (files[i].number - files[i - 1].number > step) {
      throw InputError(cat(source.dir, ": ", what, " slice ", files[i - 1].number + step,
                           " is missing (", fs::path(files[i - 1].path).filename().string(),
                           " is followed by ", fs::path(files[i].path).filename().string(), "); ",
                           what, " slices are placed along z by their position in the ", what,
                           " stack"));
    }
  }
}

std::vector<SliceFile> stack_slices(const Config& config) {
  std::vector<SliceFile> files = list_slices(config.rgb);
  // Colour slice k lies at z = slot_k · spacing_mm[2], its slot from its file number (slice_z.h).
  place_colour_slices(config, files);
  // CT slice j lies at z = ct.z_offset_mm + j · ct.slice_spacing_mm (slice_z.h): placed by its
  // position in the CT stack, so a CT slice missing inside the CT stack would shift every later
  // one (docs/RELIABILITY.md).
  if (config.ct) check_no_missing_slice(*config.ct, list_slices(*config.ct), "CT");
  // Never a silent mispairing along z (ConfigError when an input covers less than half
  // of the colour stack).
  z_extent_warnings(config, colour_slot_count(files));
  return files;
}

std::string colour_gap_warning(const Config& config, const std::vector<SliceFile>& colour) {
  const std::vector<MissingColourSlice> missing = missing_colour_slices(config, colour);
  if (missing.empty()) return "";
  // The files on either side of the first gap.
  const MissingColourSlice& first = missing.front();
  std::size_t after = 1;
  while (after < colour.size() && colour[after].slot < first.slot)
    ++after;
  return cat(config.rgb.dir, ": colour slice ", first.name, " is missing (",
             fs::path(colour[after - 1].path).filename().string(), " is followed by ",
             fs::path(colour[after].path).filename().string(), ")",
             missing.size() > 1 ? cat(" and ", missing.size() - 1, " more") : "",
             ": every colour slice keeps its z from its file number (",
             config.ct || config.seg ? "the CT and the segmentation are paired by it; " : "",
             "the packed volume has an empty slice there, listed in its slices.missing_slices)");
}

std::vector<std::string> z_extent_warnings(const Config& config, int colour_count) {
  const int ct_count = config.ct ? int(list_slices(*config.ct).size()) : 0;
  const int seg_count =
      config.seg && config.seg->slice_spacing_mm ? int(list_slices(*config.seg).size()) : 0;
  return check_z_extents(config, colour_count, ct_count, seg_count);
}

StackTransforms read_stack_transforms(const Config& config, int slice_count) {
  const std::string path = transforms_path(config);
  if (!fs::exists(path)) throw InputError(cat(path, ": missing; run vispack-register first"));
  StackTransforms transforms = read_transforms(path);
  if (int(transforms.slices.size()) != slice_count) {
    // Name the slice at fault: one that transforms.json lists but the folder lacks (a slice
    // deleted since register ran), else one the folder has but transforms.json lacks (added).
    std::set<std::string> now;
    for (const auto& f : stack_slices(config))
      now.insert(fs::path(f.path).filename().string());
    std::set<std::string> then;
    for (const auto& s : transforms.slices) {
      then.insert(s.file);
      if (!s.file.empty() && !now.count(s.file))
        throw InputError(cat((fs::path(config.rgb.dir) / s.file).string(),
                             ": slice is gone since vispack-register ran (", path, " has ",
                             transforms.slices.size(), " slices, the stack has ", slice_count,
                             "); rerun vispack-register"));
    }
    for (const auto& name : now)
      if (!then.count(name))
        throw InputError(cat((fs::path(config.rgb.dir) / name).string(),
                             ": slice is new since vispack-register ran (", path, " has ",
                             transforms.slices.size(), " slices, the stack has ", slice_count,
                             "); rerun vispack-register"));
    throw InputError(cat(path, ": has ", transforms.slices.size(), " slices but the stack has ",
                         slice_count, "; rerun vispack-register"));
  }
  return transforms;
}

StackInputs read_stack_inputs(const Config& config) {
  StackInputs inputs;
  inputs.rgb = stack_slices(config);
  if (config.ct) inputs.ct = list_slices(*config.ct);
  inputs.transforms = read_stack_transforms(config, int(inputs.rgb.size()));
  return inputs;
}

Fingerprint intermediates_fingerprint(const Config& config, const StackInputs& inputs) {
  Fingerprint fp;
  fp.text("intermediates-v2");          // v2: colour and CT rebuilt from the inputs
  fp.content(transforms_path(config));  // by its bytes: shards may rewrite it (fingerprint.h)
  for (const auto& f : inputs.rgb)
    fp.file(f.path);
  for (const auto& f : inputs.ct)
    fp.file(f.path);
  const int n = int(inputs.rgb.size());
  for (int k = 0; k < n; ++k) {
    fp.file(mask_path(config, k));
    if (config.seg) fp.file(labels_path(config, k));
  }
  return fp;
}

}  // namespace vispack::pipeline

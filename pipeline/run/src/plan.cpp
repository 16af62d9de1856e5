// plan_run: the dry run of vispack-run --plan (plan.h).
#include "vispack/pipeline/run/plan.h"

#include <filesystem>
#include <utility>

#include "vispack/common/error.h"
#include "vispack/pipeline/core/layout_check.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/labels/labels_stage.h"
#include "vispack/pipeline/run/run.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

namespace {

// Reads the first and the last slice of `files`; the last must have the first's size when
// `same_size` (the colour stack, with register's message).
PlannedInput open_ends(const std::string& name, const SliceSource& source,
                       const std::vector<SliceFile>& files, bool same_size) {
  PlannedInput in;
  in.name = name;
  in.slices = int(files.size());
  if (files.empty()) return in;
  const cv::Mat first = read_slice(files.front().path, source.raw);
  in.width = first.cols;
  in.height = first.rows;
  in.first = fs::path(files.front().path).filename().string();
  in.last = fs::path(files.back().path).filename().string();
  if (files.size() > 1) {
    const cv::Mat last = read_slice(files.back().path, source.raw);
    if (same_size && last.size() != first.size())
      throw InputError(cat(files.back().path, ": slice is ", last.cols, "x", last.rows,
                           ", the stack (", files.front().path, ") is ", first.cols, "x",
                           first.rows));
  }
  return in;
}

}  // namespace

Plan plan_run(const Config& config) {
  Plan plan;
  // The colour stack with the CT's missing-slice and z-extent checks (work_layout.h).
  const std::vector<SliceFile> stack = stack_slices(config);
  plan.slices = int(stack.size());
  for (const auto& name : pipeline_stage_names()) {
    if (name == "labels" && !config.seg) continue;
    if (name == "vdb" && (!config.vdb.enabled || config.vdb_output.empty())) continue;
    plan.stages.push_back(name);
  }
  plan.pack_slab_slices = colour_slot_count(stack) == plan.slices ? config.pack.brick_edge : 0;
  plan.warnings = z_extent_warnings(config, colour_slot_count(stack));
  if (std::string gap = colour_gap_warning(config, stack); !gap.empty())
    plan.warnings.push_back(std::move(gap));

  plan.inputs.push_back(open_ends("rgb", config.rgb, stack, true));
  if (!stack.empty()) {
    // The register stage's checks of a raw colour stack, on the same slice it reads.
    const std::string& middle = stack[stack.size() / 2].path;
    check_raw_layout(config.rgb, "rgb.raw.layout", middle, config.path);
    check_raw_size(config.rgb, "rgb.raw", middle, config.path);
  }
  if (config.ct) plan.inputs.push_back(open_ends("ct", *config.ct, list_slices(*config.ct), false));
  if (config.seg) {
    const std::vector<SliceFile> seg = list_slices(*config.seg);
    if (config.seg->slice_spacing_mm)
      check_no_missing_slice(*config.seg, seg, "segmentation");
    else
      check_seg_numbers_match(config, stack, seg);
    plan.inputs.push_back(open_ends("seg", *config.seg, seg, false));
  }
  return plan;
}

std::string format_plan(const Plan& plan) {
  std::string out = cat("slices ", plan.slices, "\nstages");
  for (const auto& stage : plan.stages)
    out += " " + stage;
  out += cat("\npack_slab_slices ", plan.pack_slab_slices, "\n");
  for (const auto& in : plan.inputs) {
    out += cat("input ", in.name, " ", in.slices, " slice", in.slices == 1 ? "" : "s");
    if (in.slices > 0)
      out += cat(", ", in.width, " x ", in.height, " px, read ", in.first,
                 in.slices > 1 ? cat(" and ", in.last) : std::string());
    out += "\n";
  }
  return out;
}

}  // namespace vispack::pipeline

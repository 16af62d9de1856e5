// The plan every pack derives from the config and the work folder before it reads a slice (a
// whole-stack pack, a shard and a merge alike: pipeline/pack/pack.h), and the report they share.
// Private to pipeline/pack. It reads no image itself: the body bounds of a cropped pack come from
// the caller (the masks for a pack, the slab files' headers for a merge), so a merge links no
// image library (vispack-merge starts in a fraction of vispack-pack's time).
// Thread-safety: plain values and free functions; no shared state.
#pragma once

#include <functional>
#include <set>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "vispack/format/writer.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/palette.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"

namespace vispack::pipeline::detail {

// Everything a pack (whole, shard or merge) derives from the config and the work folder before
// reading any slice: the writer options with the metadata, and the input fingerprint.
struct PackPlan {
  // The output depth: the colour slots the stack spans (slice_z.h colour_slot_count). Output z is
  // the slot, so a colour file missing inside the stack is an empty slice at its own z
  // (docs/ARCHITECTURE.md "Each input at its own z"); without a gap n is the stack's size.
  int n = 0;
  int stack = 0;                // colour files (stack slices)
  std::vector<int> stack_at_z;  // per output z: the stack slice there, or -1 (an empty slot)
  int f = 1;
  StackInputs inputs;  // the input slice lists and transforms.json (work_layout.h)
  cv::Size full, out_size;
  cv::Rect box;          // the part of the full-resolution output grid packed (pack.crop_margin_px)
  cv::Rect body;         // with pack.crop_margin_px: the union of the body masks' bounding boxes
                         // (full-resolution pixels; empty without a crop or without body)
  bool cropped = false;  // box is smaller than the grid
  nlohmann::json crop_meta;  // metadata "crop" (null without a crop)
  bool has_ct = false, has_labels = false;
  format::WriterOptions wo;
  std::vector<PaletteEntry> palette;
  std::vector<int> missing, black, duplicated;  // missing: file numbers absent inside the stack
  std::size_t missing_slices = 0;  // colour slots no file fills (slice_z.h), letters included
  std::string input;               // the whole pack's input fingerprint (a merge records the same)
};

// The output z range [slot of A, slot of B) of the stack range [A, B) (slice_z.h
// colour_slots_of_stack_range: ranges that tile the stack tile the volume), and the stack range
// whose files lie in an output z range (for messages naming the --slices shard to run).
SliceRange output_z_of_stack_range(const PackPlan& plan, SliceRange stack);
SliceRange stack_range_of_output_z(const PackPlan& plan, SliceRange z);

// The union of the body masks' bounding boxes over the stack's `slice_count` slices of the
// full-resolution frame `full` (empty when no slice has body); asked only when
// pack.crop_margin_px is set.
using BodyBoundsSource = std::function<cv::Rect(int slice_count, cv::Size full)>;

// The whole pack's input fingerprint: every intermediate it reads as the work folder holds them
// now, the palette and the output path.
std::string pack_input_fingerprint(const Config& config, const StackInputs& inputs);

// Lists the stack and reads transforms.json, the palette (or the labels report's IDs) and the
// overrides; builds the writer options and metadata. Throws InputError / ConfigError naming the
// file at fault.
PackPlan plan_pack(const Config& config, const StageOptions& options,
                   const BodyBoundsSource& body_bounds);

// The report and quality fields every pack that wrote config.output shares.
void report_pack(StageRun& run, const Config& config, const PackPlan& plan,
                 const std::set<std::uint16_t>& ids_seen, std::uint64_t bytes);

// The config sections the pack stage's work depends on (its StageRun's).
extern const std::vector<std::string> kPackSections;

}  // namespace vispack::pipeline::detail

#include "pack_plan.h"

#include <algorithm>
#include <filesystem>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/pipeline/core/fingerprint.h"
#include "vispack/pipeline/core/overrides.h"
#include "vispack/pipeline/core/palette.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/version.h"

namespace vispack::pipeline::detail {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

std::string hash_of_file_or_empty(const std::string& path) {
  if (path.empty() || !fs::exists(path)) return "";
  return hex64(xxh64_file(path));
}

}  // namespace

const std::vector<std::string> kPackSections = {"pack", "spacing_mm", "name", "rgb", "ct", "seg"};

std::string pack_input_fingerprint(const Config& config, const StackInputs& inputs) {
  Fingerprint fp = intermediates_fingerprint(config, inputs);
  if (config.seg && !config.seg->palette.empty()) fp.file(config.seg->palette);
  fp.text(config.output);
  return fp.str();
}

namespace {

// The part of the registered frame packed: all of it, or (pack.crop_margin_px) the union of the
// body masks plus the margin, its corners moved out to multiples of f so that the cropped grid
// is a sub-box of the uncropped one, downsampling included. Sets plan.full, body, box, cropped,
// crop_meta and out_size.
void plan_crop(const Config& config, const BodyBoundsSource& body_bounds, PackPlan& plan) {
  const int n = plan.n, f = plan.f;
  const StackTransforms& transforms = plan.inputs.transforms;
  const cv::Size full(transforms.width, transforms.height);
  cv::Rect box(0, 0, full.width, full.height);
  json crop_meta = nullptr;
  if (config.pack.crop_margin_px) {
    const int margin = *config.pack.crop_margin_px;
    const cv::Rect body = body_bounds(plan.stack, full);
    plan.body = body;
    if (body.area() > 0) {
      const int x0 = std::max(0, body.x - margin) / f * f;
      const int y0 = std::max(0, body.y - margin) / f * f;
      const int x1 = std::min(full.width, (body.br().x + margin + f - 1) / f * f);
      const int y1 = std::min(full.height, (body.br().y + margin + f - 1) / f * f);
      box = cv::Rect(x0, y0, x1 - x0, y1 - y0);
    }
    crop_meta = {{"margin_px", margin},
                 {"body_found", body.area() > 0},
                 {"box_px", {box.x, box.y, box.width, box.height}},
                 {"uncropped_dims", {(full.width + f - 1) / f, (full.height + f - 1) / f, n}}};
  }
  const cv::Size out_size((box.width + f - 1) / f, (box.height + f - 1) / f);
  plan.full = full;
  plan.box = box;
  plan.cropped = box.size() != full;
  plan.crop_meta = crop_meta;
  plan.out_size = out_size;
}

// The writer's grid (dims, spacing, origin in mm), bricks, compression, threads and channels.
void plan_writer(const Config& config, const StageOptions& options, PackPlan& plan) {
  const int n = plan.n, f = plan.f;
  const cv::Size out_size = plan.out_size;
  const cv::Rect box = plan.box;
  format::WriterOptions& wo = plan.wo;
  wo.dims = {out_size.width, out_size.height, n};
  wo.spacing_mm = {config.spacing_mm[0] * f, config.spacing_mm[1] * f, config.spacing_mm[2]};
  // Voxel (0, 0) of a downsampled grid is centred on the middle of its f x f block; a crop moves
  // it by the box's corner (full-resolution pixels).
  wo.origin_mm = {config.spacing_mm[0] * ((f - 1) / 2.0 + box.x),
                  config.spacing_mm[1] * ((f - 1) / 2.0 + box.y), 0.0};
  wo.brick_edge = config.pack.brick_edge;
  wo.zstd_level = std::max(1, config.pack.zstd_level);
  wo.compress = config.pack.zstd_level > 0;
  wo.threads = options.threads > 0 ? options.threads : config.pack.threads;
  wo.channels.push_back({"rgba", format::ChannelType::kRgba8});
  if (plan.has_ct) wo.channels.push_back({"ct", format::ChannelType::kInt16});
  if (plan.has_labels) wo.channels.push_back({"labels", format::ChannelType::kUint16});
}

// Label table: the palette, or the IDs found in the labels stage report.
void plan_labels(const Config& config, PackPlan& plan) {
  if (!plan.has_labels) return;
  format::WriterOptions& wo = plan.wo;
  std::vector<PaletteEntry>& palette = plan.palette;
  if (!config.seg->palette.empty()) {
    palette = read_palette(config.seg->palette);
  } else {
    std::string report = stage_dir(config, "labels") + "/report.json";
    if (fs::exists(report)) {
      json r = json::parse(read_file(report));
      for (auto& id : r.value("ids_present", json::array()))
        palette.push_back({id.get<std::uint16_t>(), cat("label ", id.get<int>()), {0, 0, 0}});
    }
  }
  for (const auto& e : palette)
    if (e.id != 0) wo.label_table.push_back({e.id, e.name, e.colour});
}

// Metadata: slices, registration quality, provenance (content hashes only: reproducible). Sets
// plan.missing, black and duplicated too.
void plan_metadata(const Config& config, PackPlan& plan) {
  const int n = plan.stack, f = plan.f;
  const bool has_ct = plan.has_ct, has_labels = plan.has_labels;
  const std::vector<SliceFile>& stack = plan.inputs.rgb;
  const StackTransforms& transforms = plan.inputs.transforms;
  const std::string tpath = transforms_path(config);
  const json& crop_meta = plan.crop_meta;
  format::WriterOptions& wo = plan.wo;
  json slices_meta = json::object();
  std::vector<int> numbers, jumps;
  std::vector<int>&missing = plan.missing, &black = plan.black, &duplicated = plan.duplicated;
  double q_sum = 0, q_min = 1;
  // Black, duplicated and jump slices: stack indices in the report, output z (the slot) in the
  // volume's metadata (the viewer samples across the black ones, lost_slices.h).
  std::vector<int> black_z, duplicated_z, jumps_z;
  for (int k = 0; k < n; ++k) {
    numbers.push_back(stack[k].number);
    const auto& t = transforms.slices[k];
    const int z = stack[std::size_t(k)].slot;
    if (t.black) black.push_back(k), black_z.push_back(z);
    if (t.duplicate_of) duplicated.push_back(k), duplicated_z.push_back(z);
    if (t.jump) jumps.push_back(k), jumps_z.push_back(z);
    q_sum += t.quality;
    q_min = std::min(q_min, t.quality);
  }
  for (int k = 1; k < n; ++k)
    for (int m = numbers[k - 1] + 1; m < numbers[k] && missing.size() < 100000; ++m)
      missing.push_back(m);
  // Every colour slot no file fills (slice_z.h): a missing number, or with {n}{a} a missing
  // letter ("1002b"), each a slice the volume lacks.
  // Each is an empty slice of the volume at its own z (missing_z): colour 0 with alpha 0, labels 0,
  // CT cleared (docs/ARCHITECTURE.md "Each input at its own z").
  std::vector<std::string> missing_slices;
  std::vector<int> missing_z;
  for (const auto& m : missing_colour_slices(config, stack)) {
    missing_slices.push_back(m.name);
    missing_z.push_back(m.slot);
  }
  plan.missing_slices = missing_slices.size();
  std::string names;
  for (const auto& s : stack)
    names += cat(fs::path(s.path).filename().string(), ":", fs::file_size(s.path), "\n");
  json raw_config = config.raw_json;
  // A person's registration corrections (register.overrides) travel with the volume.
  json overrides = json::array();
  if (!config.registration.overrides.empty())
    for (const auto& o : read_overrides(config.registration.overrides, n))
      overrides.push_back(to_json(o));
  wo.extra_metadata = {
      {"name", config.name},
      {"slices",
       {{"count", n},
        {"depth", plan.n},
        {"first_number", n ? numbers.front() : 0},
        {"numbers", numbers},
        {"missing_numbers", missing},
        {"missing_slices", missing_slices},
        {"missing_z", missing_z},
        {"black", black_z},
        {"duplicated", duplicated_z}}},
      {"registration",
       {{"mean_quality", n ? q_sum / n : 0.0},
        {"min_quality", q_min},
        {"jumps", jumps_z},
        {"frame", transforms.extra.value("frame", "slice0")},
        {"overrides", overrides}}},
      {"downsample", f},
      {"alpha", "body mask coverage (work/mask), 0..255"},
      {"outside_body",
       {{"rgb", config.pack.keep_colour_outside_body ? "kept" : "cleared to 0"},
        {"ct", !has_ct                            ? "no CT"
               : config.pack.keep_ct_outside_body ? "kept"
                                                  : "cleared to -1024 HU"}}},
      {"missing_slice",
       {{"rgb", "0, alpha 0"},
        {"ct", has_ct ? "-1024 HU (no colour slice, no transform, no mask: cleared as outside the "
                        "body, never interpolated)"
                      : "no CT"},
        {"labels", has_labels ? "0" : "no labels"}}},
      {"crop", crop_meta},
      {"provenance",
       {{"tool", "vispack-pack"},
        {"vispack_version", version_string()},
        {"config_hash", config_section_hash(config, {"name", "spacing_mm", "rgb", "ct", "seg",
                                                     "register", "mask", "pack"})},
        {"input_hashes",
         {{"transforms", hash_of_file_or_empty(tpath)},
          {"palette", has_labels ? hash_of_file_or_empty(config.seg->palette) : ""},
          {"id_map", has_labels ? hash_of_file_or_empty(config.seg->id_map) : ""},
          {"overrides", config.registration.overrides.empty()
                            ? std::string()
                            : hash_of_file_or_empty(config.registration.overrides)},
          {"rgb_names_sizes", hex64(xxh64(names.data(), names.size()))}}}}}};
}

}  // namespace

SliceRange output_z_of_stack_range(const PackPlan& plan, SliceRange stack) {
  return colour_slots_of_stack_range(plan.inputs.rgb, stack);
}

SliceRange stack_range_of_output_z(const PackPlan& plan, SliceRange z) {
  return stack_range_of_colour_slots(plan.inputs.rgb, z);
}

PackPlan plan_pack(const Config& config, const StageOptions& options,
                   const BodyBoundsSource& body_bounds) {
  PackPlan plan;
  plan.inputs = read_stack_inputs(config);
  plan.stack = int(plan.inputs.rgb.size());
  plan.n = colour_slot_count(plan.inputs.rgb);
  plan.stack_at_z.assign(std::size_t(plan.n), -1);
  for (int k = 0; k < plan.stack; ++k)
    plan.stack_at_z[std::size_t(plan.inputs.rgb[std::size_t(k)].slot)] = k;
  plan.has_ct = config.ct.has_value();
  plan.has_labels = config.seg.has_value();
  // One unit of work: its input fingerprint covers every intermediate read.
  plan.input = pack_input_fingerprint(config, plan.inputs);
  plan.f = config.pack.downsample;
  plan_crop(config, body_bounds, plan);
  plan_writer(config, options, plan);
  plan_labels(config, plan);
  plan_metadata(config, plan);
  return plan;
}

void report_pack(StageRun& run, const Config& config, const PackPlan& plan,
                 const std::set<std::uint16_t>& ids_seen, std::uint64_t bytes) {
  std::vector<std::uint16_t> unknown;
  std::set<std::uint16_t> table;
  for (const auto& e : plan.palette)
    table.insert(e.id);
  for (auto id : ids_seen)
    if (!table.count(id)) unknown.push_back(id);
  run.set_report("output", config.output);
  run.set_report("dims", {plan.out_size.width, plan.out_size.height, plan.n});
  run.set_report("crop", plan.crop_meta);
  run.set_report("output_bytes", std::uint64_t(fs::file_size(config.output)));
  run.set_report("input_bytes", bytes);
  run.set_quality("label_ids_not_in_table", unknown);
  run.set_quality("black_slices", plan.black);
  run.set_quality("duplicated_slices", plan.duplicated);
  run.set_quality("missing_numbers", plan.missing.size());
  run.set_quality("missing_slices", plan.missing_slices);
}

}  // namespace vispack::pipeline::detail

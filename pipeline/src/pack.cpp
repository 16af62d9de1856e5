#include "vispack/pipeline/pack.h"

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <memory>
#include <set>
#include <stdexcept>
#include <tuple>

#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/parallel.h"
#include "vispack/common/test_pause.h"
#include "vispack/common/zero_paged_buffer.h"
#include "vispack/format/downsample.h"
#include "vispack/format/writer.h"
#include "vispack/pipeline/labels.h"
#include "vispack/pipeline/opencv_threads.h"
#include "vispack/pipeline/register/solve.h"
#include "vispack/pipeline/slice_io.h"
#include "vispack/pipeline/version.h"
#include "vispack/pipeline/work_layout.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

// Most frequent ID per f x f block, by the format core's majority rule (the pyramid's rule;
// tie-break in vispack/format/downsample.h: non-zero over 0, then the smallest ID).
cv::Mat majority_downsample(const cv::Mat& labels, int f, cv::Size out) {
  cv::Mat result(out, CV_16UC1, cv::Scalar(0));
  std::vector<std::uint16_t> block;
  for (int y = 0; y < out.height; ++y)
    for (int x = 0; x < out.width; ++x) {
      block.clear();
      for (int dy = 0; dy < f && y * f + dy < labels.rows; ++dy)
        for (int dx = 0; dx < f && x * f + dx < labels.cols; ++dx)
          block.push_back(labels.at<std::uint16_t>(y * f + dy, x * f + dx));
      result.at<std::uint16_t>(y, x) = format::reduce_majority(block.data(), block.size());
    }
  return result;
}

// Colour of each f x f block weighted by the mask (the format pyramid's alpha-weighted mean,
// format/SPEC.md "Levels of detail", in floating point): a gel pixel, cleared to 0 or not, never
// tints or darkens the tissue of its block; a block without body gets the plain mean.
cv::Mat alpha_weighted_downsample(const cv::Mat& rgb, const cv::Mat& mask, cv::Size out) {
  cv::Mat a, c, weighted, plain, sum_a;
  mask.convertTo(a, CV_32F, 1.0 / 255.0);
  rgb.convertTo(c, CV_32FC3);
  cv::Mat a3;
  cv::merge(std::vector<cv::Mat>{a, a, a}, a3);
  cv::resize(c.mul(a3), weighted, out, 0, 0, cv::INTER_AREA);
  cv::resize(a, sum_a, out, 0, 0, cv::INTER_AREA);
  cv::resize(rgb, plain, out, 0, 0, cv::INTER_AREA);
  cv::Mat result(out, CV_8UC3);
  for (int y = 0; y < out.height; ++y) {
    const cv::Vec3f* w = weighted.ptr<cv::Vec3f>(y);
    const float* s = sum_a.ptr<float>(y);
    const cv::Vec3b* p = plain.ptr<cv::Vec3b>(y);
    cv::Vec3b* o = result.ptr<cv::Vec3b>(y);
    for (int x = 0; x < out.width; ++x) {
      if (s[x] <= 0.0f) {
        o[x] = p[x];
        continue;
      }
      for (int ch = 0; ch < 3; ++ch)
        o[x][ch] = cv::saturate_cast<std::uint8_t>(w[x][ch] / s[x]);
    }
  }
  return result;
}

std::string hash_of_file_or_empty(const std::string& path) {
  if (path.empty() || !fs::exists(path)) return "";
  return hex64(xxh64_file(path));
}

// Everything a pack (whole, shard or merge) derives from the config and the work folder before
// reading any slice: the writer options with the metadata, and the input fingerprint.
struct PackPlan {
  int n = 0;
  int f = 1;
  StackInputs inputs;  // the input slice lists and transforms.json (work_layout.h)
  cv::Size full, out_size;
  cv::Rect box;          // the part of the full-resolution output grid packed (pack.crop_margin_px)
  bool cropped = false;  // box is smaller than the grid
  json crop_meta;        // metadata "crop" (null without a crop)
  bool has_ct = false, has_labels = false;
  format::WriterOptions wo;
  std::vector<PaletteEntry> palette;
  std::vector<int> missing, black, duplicated;
  std::string input;  // the whole pack's input fingerprint (a merge records the same)
};

// The whole pack's input fingerprint: every intermediate it reads as the work folder holds them
// now, the palette and the output path.
std::string pack_input_fingerprint(const Config& config, const StackInputs& inputs) {
  Fingerprint fp = intermediates_fingerprint(config, inputs);
  if (config.seg && !config.seg->palette.empty()) fp.file(config.seg->palette);
  fp.text(config.output);
  return fp.str();
}

PackPlan plan_pack(const Config& config, const StageOptions& options) {
  PackPlan plan;
  plan.inputs = read_stack_inputs(config);
  const StackInputs& inputs = plan.inputs;
  const std::vector<SliceFile>& stack = inputs.rgb;
  const int n = int(stack.size());
  plan.n = n;
  const std::string tpath = transforms_path(config);
  const StackTransforms& transforms = inputs.transforms;
  const bool has_ct = config.ct.has_value(), has_labels = config.seg.has_value();
  plan.has_ct = has_ct;
  plan.has_labels = has_labels;

  // One unit of work: its input fingerprint covers every intermediate read.
  plan.input = pack_input_fingerprint(config, inputs);

  const int f = config.pack.downsample;
  plan.f = f;
  const cv::Size full(transforms.width, transforms.height);
  // The part of the registered frame packed: all of it, or (pack.crop_margin_px) the union of
  // the body masks plus the margin, its corners moved out to multiples of f so that the cropped
  // grid is a sub-box of the uncropped one, downsampling included.
  cv::Rect box(0, 0, full.width, full.height);
  json crop_meta = nullptr;
  if (config.pack.crop_margin_px) {
    const int margin = *config.pack.crop_margin_px;
    const cv::Rect body = body_bounds(config, n, full);
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
  if (has_ct) wo.channels.push_back({"ct", format::ChannelType::kInt16});
  if (has_labels) wo.channels.push_back({"labels", format::ChannelType::kUint16});

  // Label table: the palette, or the IDs found in the labels stage report.
  std::vector<PaletteEntry>& palette = plan.palette;
  if (has_labels) {
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

  // Metadata: slices, registration quality, provenance (content hashes only: reproducible).
  json slices_meta = json::object();
  std::vector<int> numbers, jumps;
  std::vector<int>&missing = plan.missing, &black = plan.black, &duplicated = plan.duplicated;
  double q_sum = 0, q_min = 1;
  for (int k = 0; k < n; ++k) {
    numbers.push_back(stack[k].number);
    const auto& t = transforms.slices[k];
    if (t.black) black.push_back(k);
    if (t.duplicate_of) duplicated.push_back(k);
    if (t.jump) jumps.push_back(k);
    q_sum += t.quality;
    q_min = std::min(q_min, t.quality);
  }
  for (int k = 1; k < n; ++k)
    for (int m = numbers[k - 1] + 1; m < numbers[k] && missing.size() < 100000; ++m)
      missing.push_back(m);
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
        {"first_number", n ? numbers.front() : 0},
        {"numbers", numbers},
        {"missing_numbers", missing},
        {"black", black},
        {"duplicated", duplicated}}},
      {"registration",
       {{"mean_quality", n ? q_sum / n : 0.0},
        {"min_quality", q_min},
        {"jumps", jumps},
        {"frame", transforms.extra.value("frame", "slice0")},
        {"overrides", overrides}}},
      {"downsample", f},
      {"alpha", "body mask coverage (work/mask), 0..255"},
      {"outside_body",
       {{"rgb", config.pack.keep_colour_outside_body ? "kept" : "cleared to 0"},
        {"ct", !has_ct                            ? "no CT"
               : config.pack.keep_ct_outside_body ? "kept"
                                                  : "cleared to -1024 HU"}}},
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

  return plan;
}

// Per-channel buffers of `slices` slices in append_slice's convention (labels as uint16).
struct SliceBuffers {
  std::vector<std::uint8_t> rgba;
  std::vector<std::int16_t> ct;
  std::vector<std::uint16_t> labels;
  SliceBuffers(const PackPlan& plan, int slices) {
    const std::size_t plane = std::size_t(plan.out_size.width) * plan.out_size.height;
    rgba.resize(plane * 4 * std::size_t(slices));
    if (plan.has_ct) ct.resize(plane * std::size_t(slices));
    if (plan.has_labels) labels.resize(plane * std::size_t(slices));
  }
  // Channel pointers of slice `z` (0-based within the buffers), in channel order.
  std::vector<const void*> slice(const PackPlan& plan, int z) const {
    const std::size_t plane = std::size_t(plan.out_size.width) * plan.out_size.height;
    std::vector<const void*> channels = {rgba.data() + plane * 4 * std::size_t(z)};
    if (plan.has_ct) channels.push_back(ct.data() + plane * std::size_t(z));
    if (plan.has_labels) channels.push_back(labels.data() + plane * std::size_t(z));
    return channels;
  }
};

// A shard's level-0 slab of `slices` slices, channel by channel: colour and CT in append_slice's
// convention, labels already in their stored type (uint8 when the palette's IDs fit it, as
// format::stored_channels_for decides, else uint16), in fresh pages that slices' zero bytes leave
// untouched (common/zero_paged_buffer.h): outside the body the colour and labels are zero, and
// the slab is ~1 GB at 2048x1216, whose page faults were the largest part of a shard's system
// time (docs/BENCHMARKS.md "Fresh memory"). Narrowing the labels here spares encode_level0_slab
// its narrowed copy (160 MB of fresh pages a 64-slice slab).
struct SlabBuffers {
  ZeroPagedBuffer rgba, ct, labels;
  bool labels_uint8 = false;
  SlabBuffers(const PackPlan& plan, int slices) {
    const std::size_t plane = std::size_t(plan.out_size.width) * plan.out_size.height;
    rgba = ZeroPagedBuffer(plane * 4 * std::size_t(slices));
    if (plan.has_ct) ct = ZeroPagedBuffer(plane * 2 * std::size_t(slices));
    if (plan.has_labels) {
      labels_uint8 =
          format::stored_channels_for(plan.wo).back().type == format::ChannelType::kUint8;
      labels = ZeroPagedBuffer(plane * (labels_uint8 ? 1 : 2) * std::size_t(slices));
    }
  }
  // Slice `z` of the slab (stack slice `stack_slice`, for errors) := the one slice of `in`.
  // Throws InputError naming the slice and voxel when a label ID does not fit uint8 labels.
  void put(const PackPlan& plan, int z, const SliceBuffers& in, int stack_slice) {
    const std::size_t plane = std::size_t(plan.out_size.width) * plan.out_size.height;
    rgba.write(plane * 4 * std::size_t(z), in.rgba.data(), plane * 4);
    if (plan.has_ct)
      ct.write(plane * 2 * std::size_t(z), reinterpret_cast<const std::uint8_t*>(in.ct.data()),
               plane * 2);
    if (plan.has_labels && labels_uint8) {
      const std::uint16_t* ids = in.labels.data();
      const auto high = std::find_if(ids, ids + plane, [](std::uint16_t id) { return id > 255; });
      if (high != ids + plane) {
        const std::size_t at = std::size_t(high - ids);
        throw InputError(cat("slice ", stack_slice, ", channel \"labels\", voxel (",
                             at % std::size_t(plan.out_size.width), ", ",
                             at / std::size_t(plan.out_size.width), "): label ID ", *high,
                             " does not fit the stored type uint8"));
      }
      labels.write_narrowed(plane * std::size_t(z), ids, plane);
    } else if (plan.has_labels) {
      labels.write(plane * 2 * std::size_t(z),
                   reinterpret_cast<const std::uint8_t*>(in.labels.data()), plane * 2);
    }
  }
  // The channel pointers of the slab (its first slice), in channel order.
  std::vector<const void*> channels(const PackPlan& plan) const {
    std::vector<const void*> out = {rgba.data()};
    if (plan.has_ct) out.push_back(ct.data());
    if (plan.has_labels) out.push_back(labels.data());
    return out;
  }
  // The buffers behind channels(), which know their zero pages (format::encode_level0_slab).
  std::vector<const ZeroPagedBuffer*> zero_pages(const PackPlan& plan) const {
    std::vector<const ZeroPagedBuffer*> out = {&rgba};
    if (plan.has_ct) out.push_back(&ct);
    if (plan.has_labels) out.push_back(&labels);
    return out;
  }
};

// Reads stack slice k's intermediates into slice `z` of `out`, converted to the output grid;
// adds the label IDs seen to `ids_seen`. Returns the decoded bytes read.
std::uint64_t convert_pack_slice(const PackPlan& plan, Intermediates in, SliceBuffers& out, int z,
                                 std::set<std::uint16_t>& ids_seen);

std::uint64_t read_pack_slice(const Config& config, const PackPlan& plan, int k, SliceBuffers& out,
                              int z, std::set<std::uint16_t>& ids_seen) {
  return convert_pack_slice(plan, read_intermediates(config, plan.inputs, k), out, z, ids_seen);
}

// Converts one slice's intermediates (read_intermediates: cleared outside the body) to slice `z`
// of `out` on the output grid (crop, downsampling); the one conversion of the staged pack, the
// shards and the streaming run. Returns the decoded bytes the intermediates stand for.
std::uint64_t convert_pack_slice(const PackPlan& plan, Intermediates in, SliceBuffers& out, int z,
                                 std::set<std::uint16_t>& ids_seen) {
  const int f = plan.f;
  const cv::Size out_size = plan.out_size;
  const std::size_t plane = std::size_t(out_size.width) * out_size.height;
  if (plan.cropped) {
    in.rgb = in.rgb(plan.box);
    in.mask = in.mask(plan.box);
    if (plan.has_ct) in.ct = in.ct(plan.box);
    if (plan.has_labels) in.labels = in.labels(plan.box);
  }
  cv::Mat rgb = in.rgb, mask = in.mask;
  if (f > 1) rgb = alpha_weighted_downsample(rgb, mask, out_size);
  if (f > 1) cv::resize(mask, mask, out_size, 0, 0, cv::INTER_AREA);
  std::uint8_t* rgba = out.rgba.data() + plane * 4 * std::size_t(z);
  for (int y = 0; y < out_size.height; ++y) {
    const cv::Vec3b* r = rgb.ptr<cv::Vec3b>(y);
    const std::uint8_t* m = mask.ptr<std::uint8_t>(y);
    std::uint8_t* o = rgba + std::size_t(y) * out_size.width * 4;
    for (int x = 0; x < out_size.width; ++x) {
      o[4 * x] = r[x][0];
      o[4 * x + 1] = r[x][1];
      o[4 * x + 2] = r[x][2];
      o[4 * x + 3] = m[x];
    }
  }
  if (plan.has_ct) {
    std::int16_t* ct = out.ct.data() + plane * std::size_t(z);
    cv::Mat hu;
    in.ct.convertTo(hu, CV_32F, 1.0, -32768.0);
    if (f > 1) cv::resize(hu, hu, out_size, 0, 0, cv::INTER_AREA);
    for (int y = 0; y < out_size.height; ++y) {
      const float* h = hu.ptr<float>(y);
      for (int x = 0; x < out_size.width; ++x)
        ct[std::size_t(y) * out_size.width + x] = cv::saturate_cast<std::int16_t>(h[x]);
    }
  }
  if (plan.has_labels) {
    std::uint16_t* labels = out.labels.data() + plane * std::size_t(z);
    cv::Mat l = in.labels;
    if (f > 1) l = majority_downsample(l, f, out_size);
    for (int y = 0; y < out_size.height; ++y) {
      const std::uint16_t* row = l.ptr<std::uint16_t>(y);
      std::copy(row, row + out_size.width, labels + std::size_t(y) * out_size.width);
      for (int x = 0; x < out_size.width; ++x)
        if (row[x]) ids_seen.insert(row[x]);
    }
  }
  return in.bytes;
}

// The report and quality fields every pack that wrote config.output shares.
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
}

const std::vector<std::string> kPackSections = {"pack", "spacing_mm", "name", "rgb", "ct", "seg"};

// ---- Sharded pack: slab files (format/SPEC.md "Partial slab files") ----

constexpr char kSlabMagic[8] = {'\x89', 'V', 'P', 'S', '\r', '\n', '\x1a', '\n'};
constexpr std::size_t kSlabRecordSize = 48;
// 2: the slab's level-1 slices follow its bricks (the merge never decodes level 0).
constexpr int kSlabVersion = 2;
constexpr int kSlabLevel1Zstd = 1;  // zstd level of the level-1 slices

// What a slab file holds: the slab's level-0 bricks (index order) and, per stored channel, its
// level-1 slices (format::encode_level0_slab) as one zstd frame with their raw size (none for a
// single-level volume).
struct SlabContent {
  std::vector<format::EncodedBrick> bricks;
  std::vector<std::vector<std::uint8_t>> level1;  // compressed
  std::vector<std::uint64_t> level1_raw;
};

// The stack slices [first, last) of level-0 slab bz.
std::pair<int, int> slab_slices(const PackPlan& plan, std::int64_t bz) {
  const int e = plan.wo.brick_edge;
  return {int(bz) * e, std::min(plan.n, int(bz + 1) * e)};
}

// What a slab is made from: its slices' intermediates, the palette (it decides the stored label
// type) and the geometry. A merge refuses a slab file whose recorded fingerprint differs.
std::string slab_input(const Config& config, const PackPlan& plan, std::int64_t bz) {
  Fingerprint fp;
  auto [first, last] = slab_slices(plan, bz);
  // Colour and CT are rebuilt from the inputs with transforms.json (work_layout.h).
  fp.content(transforms_path(config));  // by its bytes: shards may rewrite it (fingerprint.h)
  for (int k = first; k < last; ++k) {
    fp.file(plan.inputs.rgb[std::size_t(k)].path).file(mask_path(config, k));
    if (config.ct) {
      const int ct_k = k + config.ct->slice_offset;
      fp.text(ct_k >= 0 && ct_k < int(plan.inputs.ct.size())
                  ? hex64(xxh64_file(plan.inputs.ct[std::size_t(ct_k)].path))
                  : std::string("no CT slice"));
    }
    if (config.seg) fp.file(labels_path(config, k));
  }
  if (plan.has_labels && !config.seg->palette.empty()) fp.file(config.seg->palette);
  fp.text(cat(plan.out_size.width, "x", plan.out_size.height, "x", plan.n, " box ", plan.box.x, ",",
              plan.box.y, ",", plan.box.width, ",", plan.box.height, " keep ",
              config.pack.keep_colour_outside_body, config.pack.keep_ct_outside_body));
  return fp.str();
}

std::string slab_header_json(const PackPlan& plan, const std::vector<format::ChannelSpec>& stored,
                             std::int64_t bz, std::size_t bricks, const std::string& input) {
  json channels = json::array();
  for (const auto& c : stored)
    channels.push_back({{"name", c.name}, {"type", format::channel_type_name(c.type)}});
  auto [first, last] = slab_slices(plan, bz);
  json h = {{"format", "vispack-slab"},
            {"version", kSlabVersion},
            {"bz", bz},
            {"slices", {first, last}},
            {"dims", plan.wo.dims},
            {"brick_edge", plan.wo.brick_edge},
            {"zstd_level", plan.wo.zstd_level},
            {"compress", plan.wo.compress},
            {"channels", channels},
            {"bricks", bricks},
            {"input", input}};
  return h.dump();
}

template <class T>
void put(std::string& out, T value) {
  out.append(reinterpret_cast<const char*>(&value), sizeof value);
}

void write_slab_file(const std::string& path, const std::string& header, const SlabContent& slab) {
  // Streamed to the file (the slab's payloads are ~120 MB at 2048x1216: one string of the whole
  // file cost a shard that much again in fresh pages, twice over while it grew); the trailing
  // checksum is the xxh64 of every byte before it.
  AtomicFile file(path);
  Xxh64Stream sum;
  std::string small;  // records and headers, handed to the file before each payload
  auto emit_small = [&] {
    sum.update(small.data(), small.size());
    file.write(small);
    small.clear();
  };
  auto emit = [&](const void* data, std::size_t size) {
    emit_small();
    sum.update(data, size);
    file.write(data, size);
  };
  small.assign(kSlabMagic, 8);
  put(small, std::uint32_t(header.size()));
  small += header;
  for (const auto& b : slab.bricks) {
    put(small, std::uint8_t(b.codec));
    small.append(7, '\0');
    small.append(reinterpret_cast<const char*>(b.min.data()), 8);
    small.append(reinterpret_cast<const char*>(b.max.data()), 8);
    put(small, b.checksum);
    put(small, std::uint64_t(b.payload.size()));
    put(small, std::uint32_t(b.labels.size()));
    put(small, std::uint32_t(0));
    small.append(reinterpret_cast<const char*>(b.labels.data()), b.labels.size() * 4);
    if (b.payload.size() < (std::size_t(1) << 16)) {
      small.append(reinterpret_cast<const char*>(b.payload.data()), b.payload.size());
    } else {
      emit(b.payload.data(), b.payload.size());
    }
    if (small.size() >= (std::size_t(1) << 20)) emit_small();
  }
  for (std::size_t c = 0; c < slab.level1.size(); ++c) {
    put(small, std::uint64_t(slab.level1_raw[c]));
    put(small, std::uint64_t(slab.level1[c].size()));
    emit(slab.level1[c].data(), slab.level1[c].size());
  }
  emit_small();
  const std::uint64_t checksum = sum.digest();
  file.write(&checksum, sizeof checksum);
  file.commit();
}

// A slab file opened for the merge, checked against what the merge expects (`expected_header` =
// the JSON it would write, input fingerprint aside; `level1_bytes`: the size of each channel's
// level-1 slices; `slices`: the slab's stack slices, for messages). Nothing of it is held whole:
// its trailing checksum is checked reading it once through a small buffer, its bricks' stored
// bytes stay in the file (take_bricks() gives their offsets; the format Writer copies them from
// payload_file() into the packed file, file to file), and its level-1 slices are decoded one
// slice at a time (read_level1). A 64-slice slab of 2048x1216 slices is ~130 MB, which a merge
// that read it into memory paid for in fresh pages (and zeroing) before copying it out again.
// Owns the open file (RAII); payload_file() is valid while this object lives. Throws
// FormatError / InputError / IoError naming the file.
class SlabFile {
 public:
  SlabFile(const std::string& path, const std::string& expected_header,
           const std::string& expected_input, std::pair<int, int> slices,
           const std::vector<std::size_t>& level1_bytes)
      : path_(path), file_(std::fopen(path.c_str(), "rb"), &std::fclose) {
    if (!file_) throw IoError(cat(path, ": cannot open: ", std::strerror(errno)));
    std::error_code ec;
    const std::uint64_t file_size = fs::file_size(path, ec);
    if (ec) throw IoError(cat(path, ": cannot read its size: ", ec.message()));
    {
      char magic[8] = {};
      if (file_size < 8 + 4 + 8) throw bad("not a vispack slab file (bad magic or truncated)");
      read_exactly(magic, 8);
      if (std::memcmp(magic, kSlabMagic, 8) != 0)
        throw bad("not a vispack slab file (bad magic or truncated)");
      Xxh64Stream hash;
      hash.update(magic, 8);
      std::vector<char> buffer(std::size_t(1) << 20);
      for (std::uint64_t left = file_size - 16; left > 0;) {
        const std::size_t n = std::size_t(std::min<std::uint64_t>(left, buffer.size()));
        read_exactly(buffer.data(), n);
        hash.update(buffer.data(), n);
        left -= n;
      }
      std::uint64_t sum = 0;
      read_exactly(&sum, 8);
      if (hash.digest() != sum) throw bad("checksum mismatch (corrupt or truncated)");
      if (std::fseek(file_.get(), 8, SEEK_SET) != 0) throw IoError(cat(path, ": seek failed"));
    }
    pos_ = 8;
    end_ = file_size - 8;
    std::uint32_t header_size = 0;
    take(&header_size, 4);
    if (header_size > end_ - pos_) throw bad("truncated header");
    std::string header_text(header_size, '\0');
    take(header_text.data(), header_size);
    json header = json::parse(header_text, nullptr, false);
    if (!header.is_object() || !header.contains("input")) throw bad("bad header");
    if (header.value("version", 0) != kSlabVersion) {
      throw InputError(cat(path, ": slab file version ", header.value("version", 0),
                           " (an older vispack-pack, without level-1 slices); this merge reads "
                           "version ",
                           kSlabVersion, ": rerun vispack-pack --slices ", slices.first, ":",
                           slices.second));
    }
    const std::string input = header["input"].is_string() ? header["input"].get<std::string>() : "";
    json expected = json::parse(expected_header);
    header["input"] = expected["input"];
    if (header != expected) {
      throw InputError(cat(path,
                           ": written with other pack options or another stack shape; rerun "
                           "vispack-pack --slices ",
                           slices.first, ":", slices.second));
    }
    if (input != expected_input) {
      throw InputError(cat(path, ": out of date: slices ", slices.first, ":", slices.second,
                           " changed since it was written; rerun vispack-pack --slices ",
                           slices.first, ":", slices.second));
    }
    const std::size_t count = expected["bricks"].get<std::size_t>();
    bricks_.resize(count);
    for (auto& b : bricks_) {
      std::uint8_t rec[kSlabRecordSize];
      take(rec, kSlabRecordSize);
      if (rec[0] > 2) throw bad(cat("unknown codec ", int(rec[0])));
      b.codec = format::Codec(rec[0]);
      std::memcpy(b.min.data(), rec + 8, 8);
      std::memcpy(b.max.data(), rec + 16, 8);
      std::uint64_t size = 0;
      std::uint32_t labels = 0;
      std::memcpy(&b.checksum, rec + 24, 8);
      std::memcpy(&size, rec + 32, 8);
      std::memcpy(&labels, rec + 40, 4);
      if (std::uint64_t(labels) * 4 > end_ - pos_) throw bad("truncated label set");
      b.labels.resize(labels);
      take(b.labels.data(), std::size_t(labels) * 4);
      if (size > end_ - pos_) throw bad("truncated payload");
      // Left in the file: where it is.
      b.file_offset = pos_;
      b.file_bytes = size;
      skip(size);
    }
    for (std::size_t c = 0; c < level1_bytes.size(); ++c) {
      std::uint64_t raw = 0, size = 0;
      take(&raw, 8);
      take(&size, 8);
      if (raw != level1_bytes[c])
        throw bad(
            cat("level-1 slices of channel ", c, ": ", raw, " bytes, expected ", level1_bytes[c]));
      if (size > end_ - pos_) throw bad("truncated level-1 slices");
      frames_.emplace_back(new std::uint8_t[std::size_t(size)]);
      take(frames_.back().get(), size);
      readers_.push_back(std::make_unique<format::ZstdFrameReader>(
          frames_.back().get(), std::size_t(size), cat(path, ": level-1 slices of channel ", c)));
    }
    if (pos_ != end_) throw bad("trailing bytes after the level-1 slices");
    payload_file_.fd = fileno(file_.get());
    payload_file_.name = path;
  }

  // The bricks (index order within the slab), their stored bytes at file_offset in
  // payload_file(); once.
  std::vector<format::EncodedBrick> take_bricks() { return std::move(bricks_); }
  const format::PayloadFile& payload_file() const { return payload_file_; }
  // The next `n` bytes of channel c's level-1 slices into out.
  void read_level1(std::size_t c, std::uint8_t* out, std::size_t n) { readers_[c]->read(out, n); }
  // Checks that every channel's level-1 frame ended exactly after what was read.
  void finish_level1() {
    for (auto& r : readers_)
      r->finish();
  }

 private:
  FormatError bad(const std::string& what) const { return FormatError(cat(path_, ": ", what)); }
  void read_exactly(void* dst, std::size_t n) {
    if (n > 0 && std::fread(dst, 1, n, file_.get()) != n) {
      if (std::ferror(file_.get())) throw IoError(cat(path_, ": read failed"));
      throw bad("truncated (the file shrank while being read)");
    }
  }
  void take(void* dst, std::uint64_t n) {
    if (n > end_ - pos_) throw bad("truncated");
    read_exactly(dst, std::size_t(n));  // an empty label set: no bytes (its data() may be null)
    pos_ += n;
  }
  void skip(std::uint64_t n) {
    if (n == 0) return;
    if (std::fseek(file_.get(), long(n), SEEK_CUR) != 0) throw IoError(cat(path_, ": seek failed"));
    pos_ += n;
  }

  std::string path_;
  std::unique_ptr<std::FILE, int (*)(std::FILE*)> file_;
  std::uint64_t pos_ = 0, end_ = 0;
  std::vector<format::EncodedBrick> bricks_;
  std::vector<std::unique_ptr<std::uint8_t[]>> frames_;
  std::vector<std::unique_ptr<format::ZstdFrameReader>> readers_;
  format::PayloadFile payload_file_;
};

// The bricks of channel c in a slab's brick list (channel, then by, then bx).
struct BrickSpan {
  const format::EncodedBrick* first;
  const format::EncodedBrick* last;
  const format::EncodedBrick* begin() const { return first; }
  const format::EncodedBrick* end() const { return last; }
};
BrickSpan bricks_of_channel(const std::vector<format::EncodedBrick>& bricks, std::size_t c,
                            std::int64_t per_channel) {
  const format::EncodedBrick* first = bricks.data() + c * std::size_t(per_channel);
  return {first, first + per_channel};
}

std::string slab_path(const Config& config, std::int64_t bz) {
  return slice_output_path(config, "pack-slabs", "slab", int(bz), "vpkslab");
}

// The level-0 slabs [s0, s1) a shard of stack slices [A, B) packs: those whose first slice lies
// in [A, B).
std::pair<int, int> shard_slabs(int brick_edge, SliceRange range) {
  const int e = brick_edge;
  return {(range.first + e - 1) / e, (range.last + e - 1) / e};
}

// The pack-slabs stage run of a shard's slabs [s0, s1) (one unit per slab).
std::unique_ptr<StageRun> slab_run(const Config& config, const StageOptions& options,
                                   const PackPlan& plan, int s0, int s1) {
  StageOptions unit = options;
  unit.slices = cat(s0, ":", s1);
  return std::make_unique<StageRun>(config, "pack-slabs", int(format::level0_slab_count(plan.wo)),
                                    unit, kPackSections);
}

// Encodes slab bz from `buffers` (its slices, converted) and writes and records its slab file:
// the one encoding of a pack shard, staged or streaming.
void write_slab(const Config& config, const PackPlan& plan, StageRun& run, int bz,
                const SlabBuffers& buffers, const std::string& input, std::uint64_t bytes) {
  const std::string path = slab_path(config, bz);
  SlabContent slab;
  // The level-1 slices, compressed as they are reduced (one frame per channel, channels in
  // order): never held raw.
  const auto [first, last] = slab_slices(plan, bz);
  const std::uint64_t n1 = std::uint64_t(last - first + 1) / 2;
  std::unique_ptr<format::ZstdFrameWriter> frame;
  auto level1 = [&](std::size_t c, int, const std::uint8_t* data, std::size_t bytes) {
    if (c == slab.level1_raw.size()) {
      if (frame) slab.level1.push_back(frame->finish());
      slab.level1_raw.push_back(bytes * n1);
      frame = std::make_unique<format::ZstdFrameWriter>(bytes * n1, kSlabLevel1Zstd);
    }
    frame->write(data, bytes);
  };
  slab.bricks = format::encode_level0_slab(plan.wo, bz, buffers.channels(plan), level1,
                                           format::SlabLabels::kStored, buffers.zero_pages(plan));
  if (frame) slab.level1.push_back(frame->finish());
  write_slab_file(
      path,
      slab_header_json(plan, format::stored_channels_for(plan.wo), bz, slab.bricks.size(), input),
      slab);
  if (test_pause_enabled()) test_pause_point(cat("slab:pack:", bz));  // test_pause.h
  run.done(bz, input, {path}, bytes);
}

StageResult no_slab_result(const Config& config) {
  StageResult none;
  none.stage = "pack";
  none.output = stage_dir(config, "pack-slabs");
  return none;
}

StageResult run_pack_shard(const Config& config, const StageOptions& options, const PackPlan& plan,
                           SliceRange range) {
  const auto [s0, s1] = shard_slabs(plan.wo.brick_edge, range);
  if (s0 == s1) return no_slab_result(config);
  const std::unique_ptr<StageRun> run = slab_run(config, options, plan, s0, s1);
  // Slices are read and converted on this thread with OpenCV's pool: as many as --threads.
  ScopedOpenCvThreads opencv_threads(run->threads());
  std::set<std::uint16_t> ids_seen;
  for (int bz = s0; bz < s1; ++bz) {
    const std::string input = slab_input(config, plan, bz);
    if (run->up_to_date(bz, input, {slab_path(config, bz)})) {
      run->skip(bz);
      continue;
    }
    auto [first, last] = slab_slices(plan, bz);
    SlabBuffers buffers(plan, last - first);
    SliceBuffers slice(plan, 1);
    std::uint64_t bytes = 0;
    for (int k = first; k < last; ++k) {
      bytes += read_pack_slice(config, plan, k, slice, 0, ids_seen);
      buffers.put(plan, k - first, slice, k);
    }
    write_slab(config, plan, *run, bz, buffers, input, bytes);
  }
  run->set_report("slabs", {s0, s1});
  run->set_report("slices", {range.first, range.last});
  return run->finish(run->dir());
}

StageResult run_pack_whole(const Config& config, const StageOptions& options,
                           const PackPlan& plan) {
  StageOptions unit = options;
  unit.slices.clear();
  StageRun run(config, "pack", 1, unit, kPackSections);
  run.remove_stale_temporaries_of(config.output);
  if (run.up_to_date(0, plan.input, {config.output})) {
    run.skip(0);
    return run.finish(config.output);
  }
  // Slices are read and converted on this thread with OpenCV's pool: as many as --threads.
  ScopedOpenCvThreads opencv_threads(run.threads());
  make_directories(fs::path(config.output).parent_path().string());
  format::Writer writer(config.output, plan.wo);
  SliceBuffers buffers(plan, 1);
  std::uint64_t bytes = 0;
  std::set<std::uint16_t> ids_seen;
  for (int k = 0; k < plan.n; ++k) {
    bytes += read_pack_slice(config, plan, k, buffers, 0, ids_seen);
    writer.append_slice(buffers.slice(plan, 0));
    if (test_pause_enabled()) test_pause_point(cat("append:pack:", k));  // test_pause.h
    run.add_bytes(0);
  }
  writer.finish();
  run.done(0, plan.input, {config.output}, bytes);
  report_pack(run, config, plan, ids_seen, bytes);
  return run.finish(config.output);
}

}  // namespace

StageResult run_pack_stage(const Config& config, const StageOptions& options) {
  PackPlan plan = plan_pack(config, options);
  if (!options.slices.empty()) {
    SliceRange range = parse_slice_range(options.slices, plan.n);
    if (range.first != 0 || range.last != plan.n)
      return run_pack_shard(config, options, plan, range);
  }
  return run_pack_whole(config, options, plan);
}

StageResult run_pack_merge(const Config& config, const StageOptions& options) {
  if (!options.slices.empty())
    throw UsageError("--merge builds the whole file from every shard; it takes no --slices");
  PackPlan plan = plan_pack(config, options);
  StageOptions unit = options;
  StageRun run(config, "pack", 1, unit, kPackSections);
  run.remove_stale_temporaries_of(config.output);
  if (run.up_to_date(0, plan.input, {config.output})) {
    run.skip(0);
    return run.finish(config.output);
  }
  const auto slabs = format::level0_slab_count(plan.wo);
  // Every slab file must be there before anything is written.
  for (std::int64_t bz = 0; bz < slabs; ++bz) {
    const std::string path = slab_path(config, bz);
    if (!fs::exists(path)) {
      auto [first, last] = slab_slices(plan, bz);
      throw InputError(cat(path, ": missing: the pack shard holding slices ", first, ":", last,
                           " has not run (vispack-pack --slices ", first, ":", last, ")"));
    }
  }
  make_directories(fs::path(config.output).parent_path().string());
  format::Writer writer(config.output, plan.wo);
  const std::vector<format::ChannelSpec> stored = writer.stored_channels();
  const std::int64_t e = plan.wo.brick_edge;
  const std::int64_t nx = plan.out_size.width, ny = plan.out_size.height;
  const std::int64_t gx = (nx + e - 1) / e, gy = (ny + e - 1) / e;
  const bool has_level1 = format::Writer::level_count_for(plan.wo.dims, int(e)) > 1;
  const std::size_t plane1 = std::size_t((nx + 1) / 2) * std::size_t((ny + 1) / 2);
  std::set<std::uint16_t> ids_seen;
  std::uint64_t bytes = 0;
  std::vector<std::vector<std::uint8_t>> level1_slices(stored.size());  // one slice each, reused
  std::unique_ptr<SlabFile> single_level_slab;
  for (std::int64_t bz = 0; bz < slabs; ++bz) {
    const std::string path = slab_path(config, bz);
    const auto slices = slab_slices(plan, bz);
    const std::string input = slab_input(config, plan, bz);
    const int nzv = slices.second - slices.first;
    const std::size_t n1 = has_level1 ? std::size_t(nzv + 1) / 2 : 0;
    std::vector<std::size_t> level1_bytes;
    if (has_level1)
      for (const auto& c : stored)
        level1_bytes.push_back(plane1 * n1 * format::channel_type_bytes(c.type));
    auto slab = std::make_unique<SlabFile>(
        path, slab_header_json(plan, stored, bz, std::size_t(gx * gy) * stored.size(), input),
        input, slices, level1_bytes);
    bytes += fs::file_size(path);
    std::vector<format::EncodedBrick> bricks = slab->take_bricks();
    for (std::size_t c = 0; c < stored.size(); ++c)
      for (const auto& b : bricks_of_channel(bricks, c, gx * gy))
        for (std::uint32_t id : b.labels)
          if (id) ids_seen.insert(std::uint16_t(id));
    // Level 0 as stored by the shard (never decoded: copied from its file when the Writer writes
    // the slab, at the slab's last level-1 slice, or at finish() for a single-level volume); the
    // coarser levels from its level-1 slices, decoded one slice at a time.
    writer.provide_level0_slab(bz, std::move(bricks), &slab->payload_file());
    for (std::size_t k = 0; k < n1; ++k) {
      std::vector<const void*> slice;
      for (std::size_t c = 0; c < stored.size(); ++c) {
        const std::size_t n = level1_bytes[c] / n1;
        if (level1_slices[c].size() < n) level1_slices[c].resize(n);
        slab->read_level1(c, level1_slices[c].data(), n);
        slice.push_back(level1_slices[c].data());
      }
      writer.append_level1_slice(slice);
    }
    slab->finish_level1();
    if (!has_level1) single_level_slab = std::move(slab);  // its bytes are copied at finish()
    run.add_bytes(0);
  }
  writer.finish();
  run.done(0, plan.input, {config.output}, bytes);
  report_pack(run, config, plan, ids_seen, bytes);
  run.set_report("merged_slabs", slabs);
  return run.finish(config.output);
}

// ---- PackStream: the pack fed from memory (the streaming vispack-run) ----

struct PackStream::Slice {
  SliceBuffers buffers;
  std::set<std::uint16_t> ids;
  std::uint64_t bytes = 0;
  explicit Slice(const PackPlan& plan) : buffers(plan, 1) {}
};

struct PackStream::Impl {
  const Config& config;
  PackPlan plan;
  std::unique_ptr<StageRun> run;
  std::set<std::uint16_t> ids_seen;
  std::uint64_t bytes = 0;
  int appended = 0;
  // The whole stack: the format Writer.
  std::unique_ptr<format::Writer> writer;
  // A shard (options.slices a partial range): the slices appended are range.first, ...; slabs
  // [s0, s1) are gathered in `slab` and encoded to slab files as they complete.
  bool shard = false;
  SliceRange range;
  int s0 = 0, s1 = 0;
  std::unique_ptr<SlabBuffers> slab;
  int slab_slices_held = 0;  // slices `slab` was sized for
  std::uint64_t slab_bytes = 0;
  Impl(const Config& c, const StageOptions& options) : config(c), plan(plan_pack(c, options)) {}
};

bool PackStream::streamable(const Config& config) {
  return !config.pack.crop_margin_px && (!config.seg || !config.seg->palette.empty());
}

bool PackStream::streamable(const Config& config, int stack_slices, SliceRange range) {
  if (!streamable(config)) return false;
  if (range.first == 0 && range.last == stack_slices) return true;
  const int e = config.pack.brick_edge;
  const auto [s0, s1] = shard_slabs(e, range);
  return s0 < s1 && std::min(stack_slices, s1 * e) <= range.last;
}

PackStream::PackStream(const Config& config, const StageOptions& options) {
  if (!streamable(config))
    throw UsageError("the pack needs every slice first (pack.crop_margin_px or no palette)");
  impl_ = std::make_unique<Impl>(config, options);
  Impl& d = *impl_;
  d.range = {0, d.plan.n};
  if (!options.slices.empty()) d.range = parse_slice_range(options.slices, d.plan.n);
  d.shard = d.range.first != 0 || d.range.last != d.plan.n;
  if (d.shard) {
    if (!streamable(config, d.plan.n, d.range))
      throw UsageError(cat("--slices ", options.slices, ": the pack shard's slabs (",
                           config.pack.brick_edge,
                           " slices each) do not end inside the range: give whole slabs"));
    std::tie(d.s0, d.s1) = shard_slabs(d.plan.wo.brick_edge, d.range);
    d.run = slab_run(config, options, d.plan, d.s0, d.s1);
    return;
  }
  StageOptions unit = options;
  unit.slices.clear();
  d.run = std::make_unique<StageRun>(config, "pack", 1, unit, kPackSections);
  d.run->remove_stale_temporaries_of(config.output);
  make_directories(fs::path(config.output).parent_path().string());
  d.writer = std::make_unique<format::Writer>(config.output, d.plan.wo);
}

PackStream::~PackStream() = default;

void PackStream::SliceDeleter::operator()(Slice* slice) const {
  delete slice;
}

PackStream::SlicePtr PackStream::convert(Intermediates in) const {
  SlicePtr slice(new Slice(impl_->plan));
  slice->bytes = convert_pack_slice(impl_->plan, std::move(in), slice->buffers, 0, slice->ids);
  return slice;
}

void PackStream::append(SlicePtr slice) {
  Impl& d = *impl_;
  const int k = d.range.first + d.appended;
  if (k >= d.range.last) throw std::logic_error("PackStream::append: more slices than the range");
  ++d.appended;
  d.ids_seen.insert(slice->ids.begin(), slice->ids.end());
  d.bytes += slice->bytes;
  if (!d.shard) {
    d.writer->append_slice(slice->buffers.slice(d.plan, 0));
    if (test_pause_enabled()) test_pause_point(cat("append:pack:", k));  // test_pause.h
    d.run->add_bytes(0);
    return;
  }
  // A shard: slice k into its slab's buffers; a complete slab is encoded unless up to date.
  const int bz = k / d.plan.wo.brick_edge;
  if (bz < d.s0 || bz >= d.s1) return;  // before the shard's first slab start
  const auto [first, last] = slab_slices(d.plan, bz);
  if (k == first) {
    if (!d.slab || d.slab_slices_held != last - first) {
      d.slab.reset();
      d.slab = std::make_unique<SlabBuffers>(d.plan, last - first);
      d.slab_slices_held = last - first;
    }
    d.slab_bytes = 0;
  }
  d.slab->put(d.plan, k - first, slice->buffers, k);
  d.slab_bytes += slice->bytes;
  slice.reset();
  if (k != last - 1) return;
  // The slab's masks and labels are written: its input fingerprint is final.
  const std::string input = slab_input(d.config, d.plan, bz);
  if (d.run->up_to_date(bz, input, {slab_path(d.config, bz)})) {
    d.run->skip(bz);
    return;
  }
  write_slab(d.config, d.plan, *d.run, bz, *d.slab, input, d.slab_bytes);
}

StageResult PackStream::finish() {
  Impl& d = *impl_;
  if (d.appended != d.range.size())
    throw std::logic_error(
        cat("PackStream::finish: ", d.appended, " of ", d.range.size(), " slices appended"));
  if (d.shard) {
    d.slab.reset();
    d.run->set_report("slabs", {d.s0, d.s1});
    d.run->set_report("slices", {d.range.first, d.range.last});
    return d.run->finish(d.run->dir());
  }
  d.writer->finish();
  d.writer.reset();
  // The masks and labels were written during the stream: the fingerprint a later whole pack
  // computes is the one of the work folder now, not the one plan_pack saw at the start.
  d.plan.input = pack_input_fingerprint(d.config, d.plan.inputs);
  d.run->done(0, d.plan.input, {d.config.output}, d.bytes);
  report_pack(*d.run, d.config, d.plan, d.ids_seen, d.bytes);
  return d.run->finish(d.config.output);
}

}  // namespace vispack::pipeline

#include "vispack/pipeline/pack.h"

#include <algorithm>
#include <filesystem>
#include <map>
#include <set>

#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/common/test_pause.h"
#include "vispack/format/downsample.h"
#include "vispack/format/writer.h"
#include "vispack/pipeline/labels.h"
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

}  // namespace

StageResult run_pack_stage(const Config& config, const StageOptions& options) {
  const StackInputs inputs = read_stack_inputs(config);
  const std::vector<SliceFile>& stack = inputs.rgb;
  const int n = int(stack.size());
  require_whole_stack(options, n, "vispack-pack");
  const std::string tpath = transforms_path(config);
  const StackTransforms& transforms = inputs.transforms;
  const bool has_ct = config.ct.has_value(), has_labels = config.seg.has_value();

  // One unit of work: its input fingerprint covers every intermediate read.
  Fingerprint fp = intermediates_fingerprint(config, inputs);
  if (has_labels && !config.seg->palette.empty()) fp.file(config.seg->palette);
  fp.text(config.output);
  StageOptions unit = options;
  unit.slices.clear();
  StageRun run(config, "pack", 1, unit, {"pack", "spacing_mm", "name", "rgb", "ct", "seg"});
  run.remove_stale_temporaries_of(config.output);
  const std::string input = fp.str();
  if (run.up_to_date(0, input, {config.output})) {
    run.skip(0);
    return run.finish(config.output);
  }

  const int f = config.pack.downsample;
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
  const bool cropped = box.size() != full;
  const cv::Size out_size((box.width + f - 1) / f, (box.height + f - 1) / f);

  format::WriterOptions wo;
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
  std::vector<PaletteEntry> palette;
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
  std::vector<int> numbers, missing, black, duplicated, jumps;
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

  make_directories(fs::path(config.output).parent_path().string());
  format::Writer writer(config.output, wo);
  const std::size_t plane = std::size_t(out_size.width) * out_size.height;
  std::vector<std::uint8_t> rgba(plane * 4);
  std::vector<std::int16_t> ct(plane);
  std::vector<std::uint16_t> labels(plane);
  std::uint64_t bytes = 0;
  std::set<std::uint16_t> ids_seen;
  for (int k = 0; k < n; ++k) {
    Intermediates in = read_intermediates(config, inputs, k);
    bytes += in.bytes;
    if (cropped) {
      in.rgb = in.rgb(box);
      in.mask = in.mask(box);
      if (has_ct) in.ct = in.ct(box);
      if (has_labels) in.labels = in.labels(box);
    }
    cv::Mat rgb = in.rgb, mask = in.mask;
    if (f > 1) rgb = alpha_weighted_downsample(rgb, mask, out_size);
    if (f > 1) cv::resize(mask, mask, out_size, 0, 0, cv::INTER_AREA);
    for (int y = 0; y < out_size.height; ++y) {
      const cv::Vec3b* r = rgb.ptr<cv::Vec3b>(y);
      const std::uint8_t* m = mask.ptr<std::uint8_t>(y);
      std::uint8_t* o = rgba.data() + std::size_t(y) * out_size.width * 4;
      for (int x = 0; x < out_size.width; ++x) {
        o[4 * x] = r[x][0];
        o[4 * x + 1] = r[x][1];
        o[4 * x + 2] = r[x][2];
        o[4 * x + 3] = m[x];
      }
    }
    std::vector<const void*> channels = {rgba.data()};
    if (has_ct) {
      cv::Mat hu;
      in.ct.convertTo(hu, CV_32F, 1.0, -32768.0);
      if (f > 1) cv::resize(hu, hu, out_size, 0, 0, cv::INTER_AREA);
      for (int y = 0; y < out_size.height; ++y) {
        const float* h = hu.ptr<float>(y);
        for (int x = 0; x < out_size.width; ++x)
          ct[std::size_t(y) * out_size.width + x] = cv::saturate_cast<std::int16_t>(h[x]);
      }
      channels.push_back(ct.data());
    }
    if (has_labels) {
      cv::Mat l = in.labels;
      if (f > 1) l = majority_downsample(l, f, out_size);
      for (int y = 0; y < out_size.height; ++y) {
        const std::uint16_t* row = l.ptr<std::uint16_t>(y);
        std::copy(row, row + out_size.width, labels.data() + std::size_t(y) * out_size.width);
        for (int x = 0; x < out_size.width; ++x)
          if (row[x]) ids_seen.insert(row[x]);
      }
      channels.push_back(labels.data());
    }
    writer.append_slice(channels);
    if (test_pause_enabled()) test_pause_point(cat("append:pack:", k));  // test_pause.h
    run.add_bytes(0);
  }
  writer.finish();
  run.done(0, input, {config.output}, bytes);
  std::vector<std::uint16_t> unknown;
  std::set<std::uint16_t> table;
  for (const auto& e : palette)
    table.insert(e.id);
  for (auto id : ids_seen)
    if (!table.count(id)) unknown.push_back(id);
  run.set_report("output", config.output);
  run.set_report("dims", {out_size.width, out_size.height, n});
  run.set_report("crop", crop_meta);
  run.set_report("output_bytes", std::uint64_t(fs::file_size(config.output)));
  run.set_report("input_bytes", bytes);
  run.set_quality("label_ids_not_in_table", unknown);
  run.set_quality("black_slices", black);
  run.set_quality("duplicated_slices", duplicated);
  run.set_quality("missing_numbers", missing.size());
  return run.finish(config.output);
}

}  // namespace vispack::pipeline

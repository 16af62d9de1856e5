#include "vispack/pipeline/pack/pack.h"

#include "pack_plan.h"
#include "pack_slab.h"

#include <algorithm>
#include <filesystem>
#include <memory>
#include <set>
#include <stdexcept>
#include <tuple>

#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/common/test_pause.h"
#include "vispack/common/zero_paged_buffer.h"
#include "vispack/format/downsample.h"
#include "vispack/format/writer.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/intermediates.h"
#include "vispack/pipeline/imaging/opencv_threads.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;
using namespace detail;  // pack_plan.h, pack_slab.h

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

// The plan of a pack that reads the intermediates: a crop's body bounds from the masks.
PackPlan plan_from_masks(const Config& config, const StageOptions& options) {
  return plan_pack(config, options, [&](int slice_count, cv::Size full) {
    return body_bounds(config, slice_count, full);
  });
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
  // Slice `z` := an empty slot's slice (a missing colour file, pack_plan.h): colour 0 and alpha 0,
  // labels 0, CT -1024 HU (cleared as outside the body: no colour slice, so no transform to carry
  // the CT into the frame and no mask; docs/ARCHITECTURE.md "Each input at its own z").
  void clear(const PackPlan& plan, int z) {
    const std::size_t plane = std::size_t(plan.out_size.width) * plan.out_size.height;
    std::fill_n(rgba.begin() + std::ptrdiff_t(plane * 4 * std::size_t(z)), plane * 4, 0);
    if (plan.has_ct)
      std::fill_n(ct.begin() + std::ptrdiff_t(plane * std::size_t(z)), plane, std::int16_t(-1024));
    if (plan.has_labels)
      std::fill_n(labels.begin() + std::ptrdiff_t(plane * std::size_t(z)), plane, 0);
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

// The level-0 slabs [s0, s1) a shard packs whose output z range is `range` (output_z_of_stack_range
// of its stack slices [A, B)): those whose first slice lies in it. Shards that tile the stack tile
// the output z, so every slab is packed by exactly one shard.
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
  const auto [s0, s1] = shard_slabs(plan.wo.brick_edge, output_z_of_stack_range(plan, range));
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
    for (int z = first; z < last; ++z) {
      const int k = plan.stack_at_z[std::size_t(z)];
      if (k < 0)
        slice.clear(plan, 0);
      else
        bytes += read_pack_slice(config, plan, k, slice, 0, ids_seen);
      buffers.put(plan, z - first, slice, k < 0 ? z : k);
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
  for (int z = 0; z < plan.n; ++z) {
    const int k = plan.stack_at_z[std::size_t(z)];
    if (k < 0)
      buffers.clear(plan, 0);  // a missing colour file: an empty slice at its z
    else
      bytes += read_pack_slice(config, plan, k, buffers, 0, ids_seen);
    writer.append_slice(buffers.slice(plan, 0));
    if (k >= 0 && test_pause_enabled()) test_pause_point(cat("append:pack:", k));  // test_pause.h
    run.add_bytes(0);
  }
  writer.finish();
  run.done(0, plan.input, {config.output}, bytes);
  report_pack(run, config, plan, ids_seen, bytes);
  return run.finish(config.output);
}

}  // namespace

StageResult run_pack_stage(const Config& config, const StageOptions& options) {
  PackPlan plan = plan_from_masks(config, options);
  if (!options.slices.empty()) {
    SliceRange range = parse_slice_range(options.slices, plan.stack);
    if (range.first != 0 || range.last != plan.stack)
      return run_pack_shard(config, options, plan, range);
  }
  return run_pack_whole(config, options, plan);
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
  SliceRange range;    // stack slices
  SliceRange z_range;  // their output z (output_z_of_stack_range)
  int next_z = 0;      // the next output z to place (empty slots before a slice are placed first)
  int s0 = 0, s1 = 0;
  std::unique_ptr<SlabBuffers> slab;
  int slab_slices_held = 0;  // slices `slab` was sized for
  std::uint64_t slab_bytes = 0;
  std::unique_ptr<SliceBuffers> empty;  // an empty slot's slice, made at the first one
  Impl(const Config& c, const StageOptions& options)
      : config(c), plan(plan_from_masks(c, options)) {}
  // Places output slices z = next_z, ... up to `until` (exclusive) as empty slots.
  void place_empty_until(int until) {
    while (next_z < until) {
      if (!empty) {
        empty = std::make_unique<SliceBuffers>(plan, 1);
        empty->clear(plan, 0);
      }
      place(next_z, *empty, 0, next_z);
    }
  }
  // Places output slice `z` (= next_z; `stack_slice`: the stack slice there, for messages).
  void place(int z, const SliceBuffers& buffers, std::uint64_t slice_bytes, int stack_slice);
};

bool PackStream::streamable(const Config& config) {
  return !config.pack.crop_margin_px && (!config.seg || !config.seg->palette.empty());
}

bool PackStream::streamable(const Config& config, const std::vector<SliceFile>& stack,
                            SliceRange range) {
  if (!streamable(config)) return false;
  if (range.first == 0 && range.last == int(stack.size())) return true;
  const int e = config.pack.brick_edge;
  const SliceRange z = colour_slots_of_stack_range(stack, range);
  const auto [s0, s1] = shard_slabs(e, z);
  return s0 < s1 && std::min(colour_slot_count(stack), s1 * e) <= z.last;
}

PackStream::PackStream(const Config& config, const StageOptions& options) {
  if (!streamable(config))
    throw UsageError("the pack needs every slice first (pack.crop_margin_px or no palette)");
  impl_ = std::make_unique<Impl>(config, options);
  Impl& d = *impl_;
  d.range = {0, d.plan.stack};
  if (!options.slices.empty()) d.range = parse_slice_range(options.slices, d.plan.stack);
  d.shard = d.range.first != 0 || d.range.last != d.plan.stack;
  d.z_range = output_z_of_stack_range(d.plan, d.range);
  d.next_z = d.z_range.first;
  if (d.shard) {
    if (!streamable(config, d.plan.inputs.rgb, d.range))
      throw UsageError(cat("--slices ", options.slices, ": the pack shard's slabs (",
                           config.pack.brick_edge,
                           " output slices each) do not end inside the range: give whole slabs"));
    std::tie(d.s0, d.s1) = shard_slabs(d.plan.wo.brick_edge, d.z_range);
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
  // The empty slots before stack slice k (missing colour files), then the slice at its own z.
  const int z = d.plan.inputs.rgb[std::size_t(k)].slot;
  d.place_empty_until(z);
  d.place(z, slice->buffers, slice->bytes, k);
}

void PackStream::Impl::place(int z, const SliceBuffers& buffers, std::uint64_t slice_bytes,
                             int stack_slice) {
  if (z != next_z) throw std::logic_error(cat("PackStream: output z ", z, " after ", next_z));
  ++next_z;
  if (!shard) {
    writer->append_slice(buffers.slice(plan, 0));
    if (test_pause_enabled()) test_pause_point(cat("append:pack:", z));  // test_pause.h
    run->add_bytes(0);
    return;
  }
  // A shard: slice z into its slab's buffers; a complete slab is encoded unless up to date.
  const int bz = z / plan.wo.brick_edge;
  if (bz < s0 || bz >= s1) return;  // before the shard's first slab start
  const auto [first, last] = slab_slices(plan, bz);
  if (z == first) {
    if (!slab || slab_slices_held != last - first) {
      slab.reset();
      slab = std::make_unique<SlabBuffers>(plan, last - first);
      slab_slices_held = last - first;
    }
    slab_bytes = 0;
  }
  slab->put(plan, z - first, buffers, stack_slice);
  slab_bytes += slice_bytes;
  if (z != last - 1) return;
  // The slab's masks and labels are written: its input fingerprint is final.
  const std::string input = slab_input(config, plan, bz);
  if (run->up_to_date(bz, input, {slab_path(config, bz)})) {
    run->skip(bz);
    return;
  }
  write_slab(config, plan, *run, bz, *slab, input, slab_bytes);
}

StageResult PackStream::finish() {
  Impl& d = *impl_;
  if (d.appended != d.range.size())
    throw std::logic_error(
        cat("PackStream::finish: ", d.appended, " of ", d.range.size(), " slices appended"));
  d.place_empty_until(d.z_range.last);  // the empty slots after the range's last file
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

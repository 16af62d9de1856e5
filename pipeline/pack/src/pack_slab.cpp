#include "pack_slab.h"

#include <algorithm>

#include <nlohmann/json.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/pipeline/core/fingerprint.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/work_layout.h"

namespace vispack::pipeline::detail {

using nlohmann::json;

namespace {

template <class T>
void put(std::string& out, T value) {
  out.append(reinterpret_cast<const char*>(&value), sizeof value);
}

}  // namespace

std::pair<int, int> slab_slices(const PackPlan& plan, std::int64_t bz) {
  const int e = plan.wo.brick_edge;
  return {int(bz) * e, std::min(plan.n, int(bz + 1) * e)};
}

std::string slab_input(const Config& config, const PackPlan& plan, std::int64_t bz) {
  Fingerprint fp;
  auto [first, last] = slab_slices(plan, bz);
  // Colour and CT are rebuilt from the inputs with transforms.json (work_layout.h).
  fp.content(transforms_path(config));  // by its bytes: shards may rewrite it (fingerprint.h)
  for (int z = first; z < last; ++z) {
    const int k = plan.stack_at_z[std::size_t(z)];
    if (k < 0) {
      fp.text("empty slot");  // a missing colour file: an empty slice (pack_plan.h)
      continue;
    }
    fp.file(plan.inputs.rgb[std::size_t(k)].path).file(mask_path(config, k));
    if (config.ct) {
      const CtAtZ at = ct_at_colour_slice(config, int(plan.inputs.ct.size()),
                                          plan.inputs.rgb[std::size_t(k)].slot);
      fp.text(at.inside() ? hex64(xxh64_file(plan.inputs.ct[std::size_t(at.below)].path))
                          : std::string("no CT slice"));
      if (at.inside() && !at.exact())
        fp.number(at.w_above).text(hex64(xxh64_file(plan.inputs.ct[std::size_t(at.above)].path)));
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
            {"crop_body_px",
             plan.crop_meta.is_null()
                 ? json(nullptr)
                 : json::array({plan.body.x, plan.body.y, plan.body.width, plan.body.height})},
            {"input", input}};
  return h.dump();
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

std::string slab_path(const Config& config, std::int64_t bz) {
  return slice_output_path(config, "pack-slabs", "slab", int(bz), "vpkslab");
}

}  // namespace vispack::pipeline::detail

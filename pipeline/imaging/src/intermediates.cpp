// The readers of work_layout.h: an intermediate checked against its expected type and size,
// the colour and CT rebuilt from the inputs, a slice's intermediates, the body bounds. Apart from
// the paths and stack listing of work_layout.cpp, so that a tool that reads no image
// (vispack-merge) links no image library.
#include <algorithm>
#include <filesystem>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/pipeline/core/output_frame.h"
#include "vispack/pipeline/core/slice_z.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/ct_resample.h"
#include "vispack/pipeline/imaging/ct_shape_blend.h"
#include "vispack/pipeline/imaging/intermediates.h"
#include "vispack/pipeline/imaging/outline.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/imaging/transforms.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

cv::Mat read_checked(const std::string& path, int type, cv::Size size) {
  if (!fs::exists(path))
    throw InputError(cat(path, ": missing intermediate (run the earlier stages first)"));
  cv::Mat m = read_slice(path);
  if (m.type() != type)
    throw InputError(cat(path, ": unexpected pixel type (expected ",
                         type == CV_8UC3   ? "8-bit RGB"
                         : type == CV_8UC1 ? "8-bit grey"
                                           : "16-bit grey",
                         ")"));
  if (m.size() != size)
    throw InputError(
        cat(path, ": is ", m.cols, "x", m.rows, ", expected ", size.width, "x", size.height));
  return m;
}

cv::Mat registered_colour(const Config& config, const StackInputs& inputs, int index) {
  const SliceFile& file = inputs.rgb.at(std::size_t(index));
  cv::Mat observed = read_slice(file.path, config.rgb.raw);
  if (observed.depth() == CV_16U) observed.convertTo(observed, CV_8U, 255.0 / 65535.0);
  if (observed.channels() == 1) cv::cvtColor(observed, observed, cv::COLOR_GRAY2RGB);
  if (observed.type() != CV_8UC3)
    throw InputError(cat(file.path, ": colour slice must be 8- or 16-bit grey or RGB"));
  const cv::Size size = grid_size(inputs.transforms);
  if (observed.size() != size)
    throw InputError(cat(file.path, ": slice is ", observed.cols, "x", observed.rows,
                         ", the stack is ", size.width, "x", size.height));
  const SliceTransform& t = inputs.transforms.slices.at(std::size_t(index));
  cv::Mat registered;
  cv::warpAffine(observed, registered,
                 cv::Mat(rigid_matrix(t.rigid, grid_centre(inputs.transforms))), size,
                 cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
  return registered;
}

cv::Mat read_ct_hu(const CtSource& ct, const std::string& path) {
  cv::Mat raw = read_slice(path, ct.raw);
  if (raw.channels() != 1) throw InputError(cat(path, ": CT slice must be single-channel"));
  cv::Mat hu;
  raw.convertTo(hu, CV_32F, ct.slope, ct.intercept);
  return hu;
}

cv::Mat CtHuCache::read(const CtSource& ct, const std::string& path) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto it = entries_.begin(); it != entries_.end(); ++it) {
      if (it->first != path) continue;
      entries_.splice(entries_.begin(), entries_, it);
      ++hits_;
      return it->second.clone();
    }
  }
  cv::Mat hu = read_ct_hu(ct, path);
  std::lock_guard<std::mutex> lock(mutex_);
  ++decoded_;
  if (capacity_ == 0) return hu;
  entries_.emplace_front(path, hu.clone());
  while (entries_.size() > capacity_)
    entries_.pop_back();
  return hu;
}

std::uint64_t CtHuCache::decoded() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return decoded_;
}

std::uint64_t CtHuCache::hits() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return hits_;
}

namespace {

cv::Mat read_hu(const CtSource& ct, const std::string& path, CtHuCache* cache) {
  return cache ? cache->read(ct, path) : read_ct_hu(ct, path);
}

}  // namespace

cv::Mat ct_hu_at_colour_slice(const Config& config, const std::vector<SliceFile>& ct_files,
                              int colour_slot, CtHuCache* cache) {
  if (!config.ct) return {};
  const CtAtZ at = ct_at_colour_slice(config, int(ct_files.size()), colour_slot);
  if (!at.inside()) return {};
  const std::string& below = ct_files[std::size_t(at.below)].path;
  cv::Mat hu = read_hu(*config.ct, below, cache);
  if (at.exact()) return hu;  // on a CT slice: that slice, as read (the 1:1 case)
  const std::string& above = ct_files[std::size_t(at.above)].path;
  const cv::Mat hu_above = read_hu(*config.ct, above, cache);
  if (hu_above.size() != hu.size())
    throw InputError(cat(above, ": CT slice is ", hu_above.cols, "x", hu_above.rows, ", ", below,
                         " is ", hu.cols, "x", hu.rows));
  // Linear in HU along z (docs/ARCHITECTURE.md "Each input at its own z" says why).
  cv::Mat blended;
  cv::addWeighted(hu, 1.0 - at.w_above, hu_above, at.w_above, 0.0, blended);
  return blended;
}

CtSlice read_ct_slice(const Config& config, const StackInputs& inputs, int index, bool for_mask,
                      CtHuCache* cache) {
  CtSlice ct;
  if (!config.ct) return ct;
  const CtAtZ at =
      ct_at_colour_slice(config, int(inputs.ct.size()), inputs.rgb[std::size_t(index)].slot);
  if (!at.inside()) return ct;
  ct.path = inputs.ct[std::size_t(at.nearest())].path;
  ct.hu = ct_hu_at_colour_slice(config, inputs.ct, inputs.rgb[std::size_t(index)].slot, cache);
  const double level = mask_edge_level_hu(config.mask.hu_threshold);
  auto neighbour_size = [&](const cv::Mat& hu, const std::string& path) {
    if (hu.size() != ct.hu.size())
      throw InputError(cat(path, ": CT slice is ", hu.cols, "x", hu.rows, ", its neighbour ",
                           ct.hu.cols, "x", ct.hu.rows));
    return hu;
  };
  if (for_mask && !at.exact()) {
    // The part rule's minimum area (mask.min_part_mm2) in CT pixels.
    const double min_part_ct_px = config.mask.min_part_mm2 /
                                  (config.ct->pixel_spacing_mm[0] * config.ct->pixel_spacing_mm[1]);
    const std::string& below_path = inputs.ct[std::size_t(at.below)].path;
    const std::string& above_path = inputs.ct[std::size_t(at.above)].path;
    const cv::Mat hu_below = read_hu(*config.ct, below_path, cache);
    const cv::Mat hu_above = read_hu(*config.ct, above_path, cache);
    const cv::Mat below = ct_body_mask(hu_below, level, min_part_ct_px);
    const cv::Mat above = ct_body_mask(hu_above, level, min_part_ct_px);
    const int n_below = cv::countNonZero(below), n_above = cv::countNonZero(above);
    ct.body_ends = n_below == 0 || n_above == 0 ||
                   cv::countNonZero(below & above) < 0.5 * std::min(n_below, n_above);
    // The outline between the two: by shape, or their union for the colour to trim.
    if (!ct.body_ends) {
      ct.shape_hu = shape_blend_hu(hu_below, hu_above, at.w_above, level);
      ct.envelope_hu = cv::max(hu_below, hu_above);
    }
    // Continuity along z: a part must be in both CT slices of the blend.
    ct.z.tissue = {ct_tissue(neighbour_size(hu_below, below_path), level),
                   ct_tissue(neighbour_size(hu_above, above_path), level)};
    ct.z.needed = 2;
  } else if (for_mask) {
    // Continuity along z: beside CT slice j, a part must continue into j − 1 or j + 1.
    for (int j : {at.below - 1, at.below + 1}) {
      if (j < 0 || j >= int(inputs.ct.size())) continue;
      const std::string& path = inputs.ct[std::size_t(j)].path;
      ct.z.tissue.push_back(
          ct_tissue(neighbour_size(read_hu(*config.ct, path, cache), path), level));
    }
    ct.z.needed = 1;
  }
  const Similarity c =
      inputs.transforms.ct_to_rgb ? *inputs.transforms.ct_to_rgb : defined_ct_to_rgb(config);
  ct.out_to_ct = output_to_ct(c, grid_centre(inputs.transforms), image_centre(ct.hu.size()));
  return ct;
}

cv::Mat resampled_ct16(const Config& config, const StackInputs& inputs, int index,
                       const CtSlice* ct, CtHuCache* cache) {
  CtSlice own;
  if (!ct) {
    own = read_ct_slice(config, inputs, index, false, cache);
    ct = &own;
  }
  if (ct->hu.empty())
    return cv::Mat(grid_size(inputs.transforms), CV_16UC1, cv::Scalar(kOutsideBodyCt16));
  return encode_hu16(resample_ct(ct->hu, ct->out_to_ct, grid_size(inputs.transforms)));
}

Intermediates read_intermediates(const Config& config, const StackInputs& inputs, int index) {
  const cv::Size size = grid_size(inputs.transforms);
  Intermediates in;
  in.rgb = registered_colour(config, inputs, index);
  in.mask = read_checked(mask_path(config, index), CV_8UC1, size);
  in.bytes = in.rgb.total() * 3 + in.mask.total();
  if (config.ct) {
    in.ct = resampled_ct16(config, inputs, index);
    in.bytes += in.ct.total() * 2;
  }
  if (config.seg) {
    in.labels = read_checked(labels_path(config, index), CV_16UC1, size);
    in.bytes += in.labels.total() * 2;
  }
  clear_outside_body(config, in);
  return in;
}

void clear_outside_body(const Config& config, Intermediates& in) {
  const cv::Size size = in.mask.size();
  // Store only what a scene needs (docs/ARCHITECTURE.md, 'The packed file'). Gel outside the body
  // varies from voxel to voxel (texture, noise), so not one brick of it would be uniform; cleared,
  // it costs nothing.
  const bool clear_rgb = !config.pack.keep_colour_outside_body;
  const bool clear_ct = config.ct && !config.pack.keep_ct_outside_body;
  if (clear_rgb || clear_ct) {
    for (int y = 0; y < size.height; ++y) {
      const std::uint8_t* m = in.mask.ptr<std::uint8_t>(y);
      cv::Vec3b* c = in.rgb.ptr<cv::Vec3b>(y);
      std::uint16_t* h = clear_ct ? in.ct.ptr<std::uint16_t>(y) : nullptr;
      for (int x = 0; x < size.width; ++x) {
        if (m[x]) continue;
        if (clear_rgb) c[x] = cv::Vec3b(0, 0, 0);
        if (h) h[x] = kOutsideBodyCt16;
      }
    }
  }
}

cv::Rect body_bounds(const Config& config, int slice_count, cv::Size size) {
  cv::Rect bounds;
  for (int k = 0; k < slice_count; ++k) {
    const cv::Rect r = cv::boundingRect(read_checked(mask_path(config, k), CV_8UC1, size));
    if (r.area() == 0) continue;
    bounds = bounds.area() == 0 ? r : (bounds | r);
  }
  return bounds;
}

}  // namespace vispack::pipeline

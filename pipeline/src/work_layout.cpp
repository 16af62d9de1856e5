#include "vispack/pipeline/work_layout.h"

#include <cstdio>
#include <filesystem>
#include <set>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/pipeline/mask.h"
#include "vispack/pipeline/register/ct_anchor.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

namespace {

std::string padded(int index) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%04d", index);
  return buffer;
}

}  // namespace

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

std::vector<SliceFile> stack_slices(const Config& config) {
  std::vector<SliceFile> files = list_slices(config.rgb);
  if (config.ct) {
    // CT slice k + slice_offset lies on colour slice k: matched by position, so a CT slice
    // missing inside the CT stack would shift every later one (issue 7). The step is the
    // smallest difference between consecutive CT numbers (1 for ct_0000, ct_0001, ...).
    const std::vector<SliceFile> ct = list_slices(*config.ct);
    int step = 0;
    for (std::size_t i = 1; i < ct.size(); ++i) {
      const int d = ct[i].number - ct[i - 1].number;
      if (step == 0 || d < step) step = d;
    }
    for (std::size_t i = 1; i < ct.size(); ++i) {
      if (ct[i].number - ct[i - 1].number > step) {
        throw InputError(cat(config.ct->dir, ": CT slice ", ct[i - 1].number + step,
                             " is missing (", fs::path(ct[i - 1].path).filename().string(),
                             " is followed by ", fs::path(ct[i].path).filename().string(),
                             "); CT slices are matched to colour slices by position"));
      }
    }
  }
  return files;
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

cv::Mat registered_colour(const Config& config, const StackInputs& inputs, int index) {
  const SliceFile& file = inputs.rgb.at(std::size_t(index));
  cv::Mat observed = read_slice(file.path, config.rgb.raw);
  if (observed.depth() == CV_16U) observed.convertTo(observed, CV_8U, 255.0 / 65535.0);
  if (observed.channels() == 1) cv::cvtColor(observed, observed, cv::COLOR_GRAY2RGB);
  if (observed.type() != CV_8UC3)
    throw InputError(cat(file.path, ": colour slice must be 8- or 16-bit grey or RGB"));
  const cv::Size size = inputs.size();
  if (observed.size() != size)
    throw InputError(cat(file.path, ": slice is ", observed.cols, "x", observed.rows,
                         ", the stack is ", size.width, "x", size.height));
  const SliceTransform& t = inputs.transforms.slices.at(std::size_t(index));
  cv::Mat registered;
  cv::warpAffine(observed, registered, cv::Mat(rigid_matrix(t.rigid, inputs.transforms.centre())),
                 size, cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
  return registered;
}

CtSlice read_ct_slice(const Config& config, const StackInputs& inputs, int index) {
  CtSlice ct;
  if (!config.ct) return ct;
  const int ct_k = index + config.ct->slice_offset;
  if (ct_k < 0 || ct_k >= int(inputs.ct.size())) return ct;
  ct.path = inputs.ct[std::size_t(ct_k)].path;
  cv::Mat raw = read_slice(ct.path, config.ct->raw);
  if (raw.channels() != 1) throw InputError(cat(ct.path, ": CT slice must be single-channel"));
  raw.convertTo(ct.hu, CV_32F, config.ct->slope, config.ct->intercept);
  const Similarity c =
      inputs.transforms.ct_to_rgb ? *inputs.transforms.ct_to_rgb : defined_ct_to_rgb(config);
  ct.out_to_ct = output_to_ct(c, inputs.transforms.centre(), image_centre(ct.hu.size()));
  return ct;
}

cv::Mat resampled_ct16(const Config& config, const StackInputs& inputs, int index,
                       const CtSlice* ct) {
  CtSlice own;
  if (!ct) {
    own = read_ct_slice(config, inputs, index);
    ct = &own;
  }
  if (ct->hu.empty()) return cv::Mat(inputs.size(), CV_16UC1, cv::Scalar(kOutsideBodyCt16));
  return encode_hu16(resample_ct(ct->hu, ct->out_to_ct, inputs.size()));
}

Fingerprint intermediates_fingerprint(const Config& config, const StackInputs& inputs) {
  Fingerprint fp;
  fp.text("intermediates-v2");          // v2: colour and CT rebuilt from the inputs (issue 12)
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

Intermediates read_intermediates(const Config& config, const StackInputs& inputs, int index) {
  const cv::Size size = inputs.size();
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
  // Issue 12: store only what a scene needs. Gel outside the body varies from voxel to voxel
  // (texture, noise), so not one brick of it would be uniform; cleared, it costs nothing.
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

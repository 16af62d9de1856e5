// The one writer of a phantom folder. See phantom_folder.h.
#include "phantom_folder.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>

#include <nlohmann/json.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vispack::phantom::detail {

namespace fs = std::filesystem;

std::string numbered(const std::string& stem, int number, int digits, const std::string& ext) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%0*d", digits, number);
  return stem + "_" + buffer + ext;
}

int file_digits(int slices) {
  return std::max(4, int(std::to_string(slices - 1).size()));
}

void check_free_space(const std::string& dir, std::uint64_t needed_bytes,
                      std::uint64_t keep_free_bytes) {
  // The folder may not exist yet: ask about its nearest existing parent.
  fs::path probe = fs::absolute(dir).lexically_normal();
  std::error_code ec;
  while (!fs::exists(probe, ec) && probe.has_parent_path() && probe != probe.parent_path())
    probe = probe.parent_path();
  const fs::space_info space = fs::space(probe, ec);
  if (ec) throw IoError(cat(probe.string(), ": cannot read the free space: ", ec.message()));
  const std::uint64_t free_bytes = space.available;
  if (free_bytes < needed_bytes || free_bytes - needed_bytes < keep_free_bytes) {
    throw IoError(cat(dir, ": needs about ", needed_bytes, " bytes (", needed_bytes / 1000000,
                      " MB)",
                      keep_free_bytes ? cat(" and ", keep_free_bytes, " bytes kept free") : "",
                      " but the file system of ", probe.string(), " has ", free_bytes, " bytes (",
                      free_bytes / 1000000, " MB) free; free space or write fewer slices"));
  }
}

PhantomFolder::PhantomFolder(std::string out_dir, int width, int height, int slices,
                             const std::array<double, 3>& spacing_mm, int digits,
                             bool truth_volumes)
    : out_dir_(std::move(out_dir)),
      width_(width),
      height_(height),
      digits_(digits),
      truth_volumes_(truth_volumes),
      plane_(std::size_t(width) * height) {
  for (const char* d : {"/rgb", "/ct", "/seg", "/truth"})
    make_directories(out_dir_ + d);
  if (!truth_volumes_) make_directories(out_dir_ + "/truth/sample");
  auto init = [&](NrrdVolume& v, NrrdType type, int components) {
    v.type = type;
    v.components = components;
    v.dims = {width, height, truth_volumes ? slices : 0};
    v.spacing_mm = spacing_mm;
    v.data.assign(v.byte_size(), 0);
  };
  init(rgb_, NrrdType::kUint8, 3);
  init(ct_, NrrdType::kInt16, 1);
  init(mask_, NrrdType::kUint8, 1);
  init(labels_, NrrdType::kUint16, 1);
  init(seg_labels_, NrrdType::kUint16, 1);
}

std::string PhantomFolder::absolute_dir() const {
  return fs::absolute(out_dir_).lexically_normal().string();
}

std::uint8_t* PhantomFolder::truth_rgb(int k) {
  return rgb_.as<std::uint8_t>() + plane_ * 3 * std::size_t(k);
}
std::int16_t* PhantomFolder::truth_ct(int k) {
  return ct_.as<std::int16_t>() + plane_ * std::size_t(k);
}
std::uint8_t* PhantomFolder::truth_mask(int k) {
  return mask_.as<std::uint8_t>() + plane_ * std::size_t(k);
}
std::uint16_t* PhantomFolder::truth_labels(int k) {
  return labels_.as<std::uint16_t>() + plane_ * std::size_t(k);
}
std::uint16_t* PhantomFolder::truth_seg_labels(int k) {
  return seg_labels_.as<std::uint16_t>() + plane_ * std::size_t(k);
}

std::string PhantomFolder::rgb_name(int k, const std::string& ext) const {
  return numbered("rgb", k, digits_, ext);
}

void PhantomFolder::write_rgb(int k, const std::string& ext, const cv::Mat& rgb) const {
  pipeline::write_image(out_dir_ + "/rgb/" + rgb_name(k, ext), rgb);
}

void PhantomFolder::write_seg(int number, const std::string& ext, const cv::Mat& seg,
                              int jpeg_quality) const {
  pipeline::write_image(out_dir_ + "/seg/" + numbered("seg", number, digits_, ext), seg,
                        jpeg_quality);
}

void PhantomFolder::write_ct(int number, const cv::Mat& ct16) const {
  pipeline::write_image(out_dir_ + "/ct/" + numbered("ct", number, digits_, ".png"), ct16);
}

void PhantomFolder::write_truth_volumes() const {
  if (!truth_volumes_) return;
  const std::string truth = out_dir_ + "/truth";
  write_nrrd(truth + "/rgb.nrrd", rgb_);
  write_nrrd(truth + "/ct.nrrd", ct_);
  write_nrrd(truth + "/mask.nrrd", mask_);
  write_nrrd(truth + "/labels.nrrd", labels_);
  write_nrrd(truth + "/seg_labels.nrrd", seg_labels_);
}

void PhantomFolder::write_truth_sample(int k, const std::uint8_t* mask,
                                       const std::uint16_t* labels) const {
  cv::Mat m(height_, width_, CV_8UC1), l(height_, width_, CV_16UC1);
  for (std::size_t i = 0; i < plane_; ++i) {
    m.data[i] = mask[i] ? 255 : 0;
    reinterpret_cast<std::uint16_t*>(l.data)[i] = labels[i];
  }
  const std::string sample = out_dir_ + "/truth/sample/";
  pipeline::write_image(sample + numbered("mask", k, digits_, ".png"), m);
  pipeline::write_image(sample + numbered("labels", k, digits_, ".png"), l);
}

void PhantomFolder::write_truth_transforms(const TruthTransforms& t) const {
  detail::write_truth_transforms(out_dir_ + "/truth/transforms.json", t);
}

void PhantomFolder::write_palette(const std::vector<PaletteEntry>& labels) const {
  nlohmann::ordered_json palette;
  palette["labels"] = nlohmann::ordered_json::array();
  for (const PaletteEntry& l : labels)
    palette["labels"].push_back({{"id", l.id}, {"name", l.name}, {"colour", l.colour}});
  write_file_atomic(out_dir_ + "/palette.json", palette.dump(2) + "\n");
}

pipeline::Config PhantomFolder::base_config(const std::string& name, const std::string& rgb_ext,
                                            const std::array<double, 2>& ct_pixel_mm,
                                            const std::string& seg_ext) const {
  const std::string base = absolute_dir();
  pipeline::Config config;
  config.path = base + "/config.json";
  config.name = name;
  config.work_dir = base + "/work";
  config.output = base + "/out/volume.vpk";
  config.vdb_output = base + "/out/volume.vdb";
  config.spacing_mm = rgb_.spacing_mm;
  config.rgb.dir = base + "/rgb";
  config.rgb.pattern = "rgb_{n}" + rgb_ext;
  pipeline::CtSource ct;
  ct.dir = base + "/ct";
  ct.pattern = "ct_{n}.png";
  ct.pixel_spacing_mm = ct_pixel_mm;
  ct.slope = 1.0;
  ct.intercept = -1024.0;
  config.ct = ct;
  pipeline::SegSource seg;
  seg.dir = base + "/seg";
  seg.pattern = "seg_{n}" + seg_ext;
  seg.palette = base + "/palette.json";
  config.seg = seg;
  return config;
}

void PhantomFolder::write_config(const pipeline::Config& config) const {
  pipeline::write_config(out_dir_ + "/config.json", config);
}

}  // namespace vispack::phantom::detail

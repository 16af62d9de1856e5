// Internal: the one writer of a phantom folder (docs/ARCHITECTURE.md "The phantom folder"),
// shared by the analytic presets (phantom.cpp) and the from-CT generator (from_ct.cpp): the slice
// folders rgb/, ct/ and seg/ with their numbered file names, the five truth volumes and
// truth/transforms.json, palette.json, and config.json through the pipeline's own config writer.
// Not installed.
//
// Thread-safety: the slice writers and the truth-volume pointers may be used from many threads at
// once for distinct slices (each slice's files and planes are its own); everything else runs on
// one thread, before or after the slices.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "phantom_model.h"
#include "truth_json.h"
#include "vispack/common/nrrd.h"
#include "vispack/pipeline/core/config.h"

namespace vispack::phantom::detail {

// "<stem>_<number, zero-padded to `digits`><ext>", the file names of every slice folder.
std::string numbered(const std::string& stem, int number, int digits, const std::string& ext);

// The digits of a stack of `slices` slices' file numbers: at least 4.
int file_digits(int slices);

// One palette entry of palette.json.
struct PaletteEntry {
  int id = 0;
  std::string name;
  std::array<int, 3> colour{};
};

// One slice of the truth volumes on the output grid (PhantomFolder::truth_planes).
struct TruthPlanes {
  std::uint8_t* rgb;
  std::int16_t* ct;
  std::uint8_t* mask;
  std::uint16_t* labels;
  // Voxel i from a model sample: colour rounded to 8 bits, HU rounded and clamped to
  // [hu_min, hu_max], body as 0/1, the label.
  void set(std::size_t i, const float sample_rgb[3], float hu, long hu_min, long hu_max, bool body,
           std::uint16_t label) const {
    for (int c = 0; c < 3; ++c)
      rgb[i * 3 + c] = to_u8(sample_rgb[c]);
    ct[i] = static_cast<std::int16_t>(std::clamp(std::lround(hu), hu_min, hu_max));
    mask[i] = body ? 1 : 0;
    labels[i] = label;
  }
};

// Throws IoError naming `dir` (or its nearest existing parent), the bytes needed and the bytes
// free when the file system holding it has fewer than needed_bytes + keep_free_bytes free.
void check_free_space(const std::string& dir, std::uint64_t needed_bytes,
                      std::uint64_t keep_free_bytes);

class PhantomFolder {
 public:
  // Creates rgb/, ct/, seg/ and truth/ under `out_dir` and the truth volumes (zeros) of
  // width × height × slices voxels at `spacing_mm`; file numbers have `digits` digits. Without
  // `truth_volumes` (a streamed folder) no volume is held: the truth_* accessors must not be
  // called, write_truth_volumes writes nothing and write_truth_sample writes truth/sample/.
  PhantomFolder(std::string out_dir, int width, int height, int slices,
                const std::array<double, 3>& spacing_mm, int digits, bool truth_volumes = true);

  int digits() const { return digits_; }
  const std::string& dir() const { return out_dir_; }
  // The folder's absolute, normalised path (what config.json's paths start with).
  std::string absolute_dir() const;

  // Slice k of each truth volume on the output grid (width × height values, rgb: 3 per pixel).
  std::uint8_t* truth_rgb(int k);
  std::int16_t* truth_ct(int k);
  std::uint8_t* truth_mask(int k);
  std::uint16_t* truth_labels(int k);
  std::uint16_t* truth_seg_labels(int k);
  TruthPlanes truth_planes(int k) {
    return {truth_rgb(k), truth_ct(k), truth_mask(k), truth_labels(k)};
  }

  // rgb/rgb_<k><ext>, seg/seg_<number><ext> and ct/ct_<number>.png (write_image's defaults, a
  // JPEG segmentation at `jpeg_quality`).
  std::string rgb_name(int k, const std::string& ext) const;
  void write_rgb(int k, const std::string& ext, const cv::Mat& rgb) const;
  void write_seg(int number, const std::string& ext, const cv::Mat& seg,
                 int jpeg_quality = 90) const;
  void write_ct(int number, const cv::Mat& ct16) const;

  // truth/rgb.nrrd, ct.nrrd, mask.nrrd, labels.nrrd, seg_labels.nrrd (none in a streamed folder).
  void write_truth_volumes() const;
  // A streamed folder's truth of slice k: truth/sample/mask_<k>.png (0/255 from the 0/1 `mask`)
  // and labels_<k>.png (16-bit IDs), width × height each.
  void write_truth_sample(int k, const std::uint8_t* mask, const std::uint16_t* labels) const;
  // truth/transforms.json (truth_json.h: the phantom's own writer).
  void write_truth_transforms(const TruthTransforms& t) const;
  // palette.json: {"labels": [{"id", "name", "colour"}, ...]}.
  void write_palette(const std::vector<PaletteEntry>& labels) const;

  // The config both generators start from: name, work folder, outputs, spacing, the rgb folder
  // (pattern rgb_{n}<rgb_ext>), the CT folder (ct_{n}.png, stored = HU + 1024, `ct_pixel_mm`) and
  // the seg folder (seg_{n}<seg_ext>, palette.json). Callers set what differs, then
  // write_config.
  pipeline::Config base_config(const std::string& name, const std::string& rgb_ext,
                               const std::array<double, 2>& ct_pixel_mm,
                               const std::string& seg_ext) const;
  // config.json through the pipeline's own writer (one writer of the schema).
  void write_config(const pipeline::Config& config) const;

 private:
  std::string out_dir_;
  int width_, height_;
  int digits_;
  bool truth_volumes_;
  NrrdVolume rgb_, ct_, mask_, labels_, seg_labels_;
  std::size_t plane_;
};

}  // namespace vispack::phantom::detail

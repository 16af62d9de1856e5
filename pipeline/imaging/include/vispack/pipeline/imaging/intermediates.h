// The one way to read a stack slice's intermediates back (pack, vdb, the one-pass stream): the
// registered colour and the resampled CT rebuilt from the inputs, the mask and labels read from
// the work folder (core/work_layout.h names the paths), what lies outside the body cleared.
// All functions are thread-safe (they only read the config and the file system, and a CtHuCache
// that guards itself).
#pragma once

#include <cstdint>
#include <list>
#include <mutex>
#include <string>
#include <utility>

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/outline.h"

namespace vispack::pipeline {

// The registered colour slice k (CV_8UC3, RGB) on the output grid: input slice k (16-bit scaled
// to 8, grey expanded to RGB) resampled with its transform (bilinear, border replicated; the
// convention of docs/ARCHITECTURE.md "Slice transforms"). The one implementation: register
// writes it when work.write_registered, mask, pack and vdb call it. Deterministic: the same
// inputs give the same bytes. Throws InputError naming the slice when its size differs.
cv::Mat registered_colour(const Config& config, const StackInputs& inputs, int index);

// A CT slice file in HU (CV_32F): stored value × ct.slope + ct.intercept. Throws InputError
// naming the file when it is not single-channel.
cv::Mat read_ct_hu(const CtSource& ct, const std::string& path);

// The CT slices in HU (read_ct_hu) decoded last, for the colour slices beside them: on a stack
// with a CT slice per colour slice, read_ct_slice(for_mask) reads CT slice j for colour slice j
// and again, for the part rule's continuity along z, for colour slices j - 1 and j + 1 (three
// decodes of each CT slice; one with this cache when the slices are read in about stack order).
// Holds the `capacity` files read last (least recently used goes first), keyed by path: one
// cache serves one run of one config (ct.slope and ct.intercept fixed). read() returns a copy
// (the caller may change it). Thread-safe: one mutex around the list, the decode outside it (two
// threads asking for one file at once both decode it).
class CtHuCache {
 public:
  explicit CtHuCache(std::size_t capacity) : capacity_(capacity) {}
  // read_ct_hu(ct, path), from the cache when it holds `path`. Throws what read_ct_hu throws.
  cv::Mat read(const CtSource& ct, const std::string& path);
  // Files decoded (cache misses) and reads answered from the cache, since construction.
  std::uint64_t decoded() const;
  std::uint64_t hits() const;

 private:
  mutable std::mutex mutex_;
  std::size_t capacity_;
  std::list<std::pair<std::string, cv::Mat>> entries_;  // most recently used first
  std::uint64_t decoded_ = 0, hits_ = 0;
};

// The CT in HU (CV_32F, CT resolution) at the z of colour slot `colour_slot` (slice_z.h:
// files[k].slot for colour slice k): the one CT slice read as is when the colour slice lies on it
// (the 1:1 case), else the two CT slices around its z blended linearly in HU; empty outside the
// CT's z range or without CT. `ct_files` is the CT stack (list_slices(*config.ct)); `cache`
// (optional) keeps decoded CT slices for the next slices (the result is the same). Throws
// InputError naming a file that is not single-channel or whose size differs from its neighbour's.
cv::Mat ct_hu_at_colour_slice(const Config& config, const std::vector<SliceFile>& ct_files,
                              int colour_slot, CtHuCache* cache = nullptr);

// The CT at output slice k's z in HU (ct_hu_at_colour_slice) and the map from output pixels to
// its pixels (imaging/transforms.h output_to_ct with transforms.json's ct_to_rgb, else the config's
// definition). Without CT, or when slice k lies outside the CT's z range, `hu` is empty.
// With `for_mask`, a slice between two CT slices is also checked for `body_ends`.
struct CtSlice {
  cv::Mat hu;
  cv::Matx23d out_to_ct{1, 0, 0, 0, 1, 0};
  std::string path;  // the CT file nearest in z; empty when none
  // The two CT slices around this z do not show one body (ct_body_mask at the mask's edge level:
  // one has none, or they overlap by less than half the smaller): a body's tip, which the blend
  // loses (a third of the way for soft tissue). The mask stage takes the colour alone there.
  bool body_ends = false;
  // With `for_mask`, between two CT slices that show one body (not body_ends), the CT for the
  // body mask (`hu` stays the HU blend: the packed ct channel). `shape_hu`: the two slices'
  // outlines interpolated by shape (ct_shape_blend.h), for a mask the colour does not refine;
  // `envelope_hu`: the larger HU of the two (their outlines' union: where the body may be), for
  // a mask the colour refines (mask.h step 4 trims it to the colour's edge). Empty otherwise: the
  // mask takes `hu`. docs/ARCHITECTURE.md "Each input at its own z" has the comparison.
  cv::Mat shape_hu;
  cv::Mat envelope_hu;
  // With `for_mask`: the neighbouring CT slices' tissue for the part rule's continuity along z
  // (outline.h ZNeighbours): beside CT slice j, j − 1 and j + 1; between two, those two.
  ZNeighbours z;
};
// `cache` (optional): as in ct_hu_at_colour_slice (the result is the same).
CtSlice read_ct_slice(const Config& config, const StackInputs& inputs, int index,
                      bool for_mask = false, CtHuCache* cache = nullptr);

// The CT of output slice k on the output grid as work/mask/ct_NNNN.png stores it (CV_16UC1,
// HU + 32768; mask.h resample_ct, encode_hu16): the one implementation the mask stage writes
// (work.write_ct) and pack and vdb read. A slice beyond the CT stack is −1024 HU (air)
// everywhere. `ct` (optional) is the slice already read; else it is read (through `cache`, when
// given).
cv::Mat resampled_ct16(const Config& config, const StackInputs& inputs, int index,
                       const CtSlice* ct = nullptr, CtHuCache* cache = nullptr);

// One output slice's intermediates, as the mask and labels stages wrote them, on the output grid,
// with what lies outside the body cleared as the config asks (pack.keep_outside_body).
struct Intermediates {
  cv::Mat rgb;              // CV_8UC3, the registered colour slice; (0, 0, 0) where mask == 0
                            // unless config.pack.keep_colour_outside_body
  cv::Mat mask;             // CV_8UC1, 0/255 body mask
  cv::Mat ct;               // CV_16UC1, HU + 32768 (empty without CT); kOutsideBodyCt16 (−1024
                            // HU, air) where mask == 0 unless config.pack.keep_ct_outside_body
  cv::Mat labels;           // CV_16UC1, label IDs (empty without segmentation)
  std::uint64_t bytes = 0;  // decoded bytes of the slices above (for throughput reports)
};

// The CT value stored outside the body when it is cleared: −1024 HU (air) as HU + 32768.
constexpr std::uint16_t kOutsideBodyCt16 = 32768 - 1024;

// The intermediates of stack slice `index` on the output grid (inputs.size()): mask and labels
// read from the work folder, each checked for size and type; colour and CT rebuilt from the
// inputs (registered_colour, resampled_ct16), whether or not the work folder holds copies.
// CT only when the config has CT and labels only when it has segmentation. Outside the
// body mask (mask == 0) colour becomes 0 and CT −1024 HU unless config.pack says to keep them
// (docs/ARCHITECTURE.md "What the packed file stores"): this is the one place where that
// happens, so the packed file and the OpenVDB export read the same values. Throws InputError
// naming the file when one is missing ("run the earlier stages first") or has the wrong size or
// pixel type.
Intermediates read_intermediates(const Config& config, const StackInputs& inputs, int index);

// An intermediate image of the work folder (a mask or label PNG), checked: throws InputError
// naming `path` when it is missing ("run the earlier stages first") or is not of `type`
// (CV_8UC1, CV_8UC3 or CV_16UC1) and `size`.
cv::Mat read_checked(const std::string& path, int type, cv::Size size);

// The clearing step of read_intermediates, for intermediates built in memory (the streaming
// vispack-run, stream.h): colour 0 and CT −1024 HU where in.mask == 0, as config.pack asks.
// `in` must hold rgb and mask (and ct when the config has CT) of one size.
void clear_outside_body(const Config& config, Intermediates& in);

// The union over stack slices [0, slice_count) of the bounding boxes of the body masks
// (<work>/mask/mask_NNNN.png, non-zero pixels), in output-grid pixels; an empty rect when no
// slice has body. Throws InputError as read_intermediates does for a missing or wrong mask.
cv::Rect body_bounds(const Config& config, int slice_count, cv::Size size);

}  // namespace vispack::pipeline

// Segmentation slices -> compact label IDs on the output grid (vispack-labels).
//
// Mode "colour": each seg pixel's RGB is looked up in the palette (palette.json:
//   { "labels": [ { "id": 1, "name": "skin", "colour": [r, g, b] }, ... ] },
// IDs 1..65535; an entry with id 0 names the background colour, black by default).
// Exact matches go through a hash map; other colours (JPEG or anti-aliasing noise) take the
// nearest palette colour (Euclidean RGB distance, k-d tree, cached per slice) if it lies within
// `seg.tolerance`; a colour farther than that from every palette colour is "unmatched": it
// is counted and its first positions are reported, or, with `seg.strict`, it is an InputError
// naming the file, the pixel and the colour (exit code 6). In non-strict mode an unmatched pixel,
// and a matched one whose nearest palette colour is more than 32 away ("unsure": JPEG chroma
// bleeding across a boundary), takes, among the IDs of the confident pixels (exact, or nearest
// within 32) in its 9x9 neighbourhood, the one whose palette colour
// is nearest to its own in YCbCr with chroma weighted 0.1 (JPEG blurs a boundary into a mix of the
// two sides' colours, and this keeps it on one of them instead of a third label); with no confident
// neighbour an unmatched pixel becomes 0 and an unsure one keeps its nearest match. Mode "id": the
// seg slices hold integer IDs (8- or 16-bit grey). With `seg.id_map` (a JSON object {"<input id>":
// <output id>}) each ID is translated; an ID missing from the map is "unmatched" (0, counted, or an
// error in strict mode). Input 0 always stays 0.
//
// The seg slices lie on the observed (drifted) grid of their colour slice. They are resampled
// onto the output grid with that slice's registration transform (work/register/transforms.json,
// transforms.h) by NEAREST neighbour only: label(q) = seg(round(p(q))), so two IDs are never
// blended. Output: work/labels/labels_NNNN.png (16-bit grey IDs) + report.json (counts of exact,
// nearest and unmatched pixels, first unmatched positions, IDs present, missing seg slices). Seg
// slices are matched to colour slices by the number in the file name, or, with
// seg.slice_spacing_mm, each colour slice takes the seg slice nearest in z (slice_z.h), resampled
// with the transform of the colour slice nearest that seg slice's z (the grid it was drawn on);
// a colour slice with no seg slice (by number, or none within half a seg spacing) gets an
// all-zero label slice and is listed in the report under "missing_seg".
//
// Thread-safety: ColourMatcher is immutable after construction and may be shared by threads;
// the other functions here are pure. The stage is in labels_stage.h.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <unordered_map>
#include <vector>

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/palette.h"
#include "vispack/pipeline/imaging/transforms.h"

namespace vispack::pipeline {

// Colour -> ID lookup: exact first, then the nearest palette colour within `tolerance`.
class ColourMatcher {
 public:
  // Adds black -> 0 unless the palette gives a colour to ID 0 or uses black for a label.
  ColourMatcher(const std::vector<PaletteEntry>& palette, double tolerance);

  struct Match {
    std::uint16_t id = 0;
    bool exact = false;
    bool matched = false;          // exact, or nearest within tolerance
    double distance = 0.0;         // to the nearest palette colour
    std::uint16_t nearest_id = 0;  // ID of the nearest palette colour, whatever the distance
  };
  Match match(std::uint8_t r, std::uint8_t g, std::uint8_t b) const;
  std::size_t size() const { return colours_.size(); }
  double tolerance() const { return tolerance_; }
  // The palette colour of `id` (black for the implicit background 0); nullptr if unknown.
  const std::array<int, 3>* colour_of(std::uint16_t id) const;

 private:
  void build(int node_begin, int node_end, int depth);
  void nearest(int begin, int end, int depth, const int q[3], int& best, int& best_d2) const;
  std::unordered_map<std::uint32_t, std::uint16_t> exact_;
  std::vector<std::array<int, 3>> colours_;  // k-d tree order (median split, implicit)
  std::vector<std::uint16_t> ids_;
  std::unordered_map<std::uint16_t, std::array<int, 3>> colour_by_id_;
  double tolerance_;
};

// Per-slice mapping statistics.
struct UnmatchedPixel {
  int x = 0, y = 0;
  std::array<int, 3> value{0, 0, 0};  // colour (mode colour) or input ID in value[0] (mode id)
  double distance = 0.0;              // to the nearest palette colour (mode colour)
};
struct LabelStats {
  std::uint64_t exact = 0, nearest = 0, unmatched = 0;
  std::vector<UnmatchedPixel> first_unmatched;  // at most kMaxReported
  static constexpr std::size_t kMaxReported = 10;
  void merge(const LabelStats& other);
};

// Maps an RGB seg slice (CV_8UC3, or CV_16UC3 reduced to 8 bits) to IDs (CV_16UC1), with the
// neighbourhood fill of unmatched pixels described above. `strict`: throws InputError naming `what`
// (the file), the pixel and colour at the first unmatched pixel.
cv::Mat map_colours(const cv::Mat& seg_rgb, const ColourMatcher& matcher, bool strict,
                    const std::string& what, LabelStats* stats);

// Maps an integer seg slice (CV_8UC1 or CV_16UC1) through `id_map` (nullptr: identity).
cv::Mat map_ids(const cv::Mat& seg_ids,
                const std::unordered_map<std::uint32_t, std::uint16_t>* id_map, bool strict,
                const std::string& what, LabelStats* stats);

// Resamples a label slice (CV_16UC1, observed grid) onto the output grid of `out_size` by nearest
// neighbour: out(q) = in(floor(p + 0.5)), p = rigid_matrix(t.rigid, center) q; outside -> 0.
cv::Mat resample_labels_nearest(const cv::Mat& labels, const SliceTransform& t,
                                const std::array<double, 2>& center_px, cv::Size out_size);

}  // namespace vispack::pipeline

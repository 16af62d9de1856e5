// QC pictures of the register stage, for a person with an image viewer:
//   draw_ct_overlay   the CT body outline (where the CT says the body is, on the output grid)
//                     drawn over the registered colour slice: if registration is right, the
//                     outline hugs the colour body.
//   plot_transforms   dx, dy and rotation of every slice over the stack: the solved curve,
//                     the CT anchors as dots (filled by confidence, hollow when down-weighted
//                     or unused), jumps as red lines, a person's overrides as orange marks,
//                     slices whose body part count or anchor confidence changes abruptly
//                     (abrupt_anchor_changes) as magenta ticks under each panel.
// Pure and thread-safe; images are RGB CV_8UC3 (write_image order).
#pragma once

#include <optional>
#include <vector>

#include <opencv2/core.hpp>

#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/ct_anchor.h"
#include "vispack/pipeline/register/solve.h"

namespace vispack::pipeline {

// `image` downsampled (INTER_AREA, both axes by the same factor) so its longer edge is at most
// `max_edge` px; a copy when it already fits.
cv::Mat shrink_to_edge(const cv::Mat& image, int max_edge);

// `registered`: the registered colour slice (RGB CV_8UC3, output grid W×H); `ct_hu`: CT slice
// (CV_32F HU) or empty (then no outline); `ct_to_rgb`: the output frame. The picture is
// downsampled so its longer edge is at most `max_edge` px; the outline is 1 px, magenta.
// `grid`: the output grid `registered` covers, when it is a smaller picture of it (the same
// field of view at fewer pixels); empty: registered.size().
cv::Mat draw_ct_overlay(const cv::Mat& registered, const cv::Mat& ct_hu,
                        const Similarity& ct_to_rgb, double hu_threshold, int max_edge = 512,
                        cv::Size grid = {});

// Slices k whose anchor changes abruptly from the previous anchored slice: the CT's or the
// colour's body part count by kAbruptParts or more, or the confidence by kAbruptConfidence or
// more (an arm or a leg lost or found, a failed match). Sorted, each once.
inline constexpr int kAbruptParts = 2;
inline constexpr double kAbruptConfidence = 0.3;
std::vector<int> abrupt_anchor_changes(const std::vector<std::optional<AnchorEstimate>>& anchors);

// The transform curves (about 1200×900 px). `anchors[k]` is slice k's anchor (may be absent);
// `overrides` marks slices a person corrected.
cv::Mat plot_transforms(const std::vector<SliceTransform>& slices,
                        const std::vector<std::optional<AnchorEstimate>>& anchors,
                        const std::vector<SliceOverride>& overrides, const std::string& title);

}  // namespace vispack::pipeline

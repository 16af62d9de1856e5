// Frame preparation for registration: each colour slice becomes a RegisterFrame once (grey
// levels for the pair estimates, the colour level of the CT anchor, fiducials, a pixel hash
// and a black flag); a frame is shared by every pair and the anchor it takes part in.
// Conventions (pixel coordinates, transforms) as in imaging/transforms.h and docs/ARCHITECTURE.md.
// All functions are pure and thread-safe.
#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline {

// A slice prepared for registration: grey float32 levels and flags. Immutable after creation.
struct RegisterFrame {
  cv::Size full_size;  // the observed slice's size
  cv::Mat coarse;      // CV_32F, longer edge ≈ 256 px (or full size if smaller), 5×5 Gaussian
  double coarse_scale = 1.0;  // coarse size / full size
  cv::Mat fine;               // CV_32F at ecc_scale, 5×5 Gaussian (may share data with coarse)
  double fine_scale = 1.0;
  // CV_32F at half of fine's scale, 5×5 Gaussian, where fine lies at least 3× above coarse
  // (the first pass of a pair's fine ECC, at a quarter of its cost a step); empty otherwise.
  cv::Mat middle;
  double middle_scale = 0.0;
  // The colour level of the CT anchor (register/ct_anchor.h): CV_32FC3 RGB in [0, 1] at
  // anchor_scale of full resolution (INTER_AREA, no blur); empty when not asked for.
  cv::Mat anchor_colour;
  double anchor_scale = 0.0;           // anchor_colour size / full size (0: none)
  bool black = false;                  // almost no signal: mean grey < 4 and standard deviation < 2
  std::uint64_t pixel_hash = 0;        // xxHash64 of the pixels (exact duplicate detection)
  std::vector<cv::Point2d> fiducials;  // find_fiducials of the slice (observed pixels)
};

// Fiducials of an RGB CV_8UC3 slice (other types: none): compact blobs that are not gel
// coloured (distance > 40 from the gel colour estimated on the slice border), lie in the gel
// (not the largest non-gel component, the body) and stay at least 2 coarse pixels inside the
// frame. Found on a level whose longer edge is about 256 px; each position is then the
// centroid, on the full-resolution slice, of the blob's coverage (the projection of each
// pixel's colour onto the gel→blob colour axis, 0.15 → 0 and 1.1 → 1, clamped). Sub-pixel
// accurate (about 0.05 px on the phantom). Returned in observed pixel coordinates, sorted by
// y then x.
std::vector<cv::Point2d> find_fiducials(const cv::Mat& rgb);

// Builds the frame from an RGB (or grey) CV_8U/CV_16U slice. `anchor_scale` in (0, 1] also
// builds anchor_colour at that fraction of full resolution (the CT anchor's working grid);
// 0 skips it. Throws InputError on an empty or unsupported image.
RegisterFrame prepare_frame(const cv::Mat& slice, const RegisterOptions& options,
                            double anchor_scale = 0.0);

}  // namespace vispack::pipeline

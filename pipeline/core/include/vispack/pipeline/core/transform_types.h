// The transform types of a slice stack as plain data, and transforms.json (the register stage's
// output and the phantom's truth), in the convention of docs/ARCHITECTURE.md ("Slice
// transforms"): Rigid for a colour slice's drift (output point q -> observed point p), Similarity
// for ct_to_rgb (CT pixel u -> output point q). No image library: the config, the overrides and
// the work folder hold these types; their matrices and the resampling are
// vispack/pipeline/imaging/transforms.h. read_transforms / write_transforms touch the file system
// (thread-safe for distinct paths).
#pragma once

#include <array>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace vispack::pipeline {

// One slice's drift: rotation about the slice centre, then shift (pixels of that slice).
struct Rigid {
  double rotation_deg = 0.0;
  double dx_px = 0.0;
  double dy_px = 0.0;
};

// Scale, rotation and shift (ct_to_rgb): scale = CT pixel size / output pixel size.
struct Similarity {
  double scale = 1.0;
  double rotation_deg = 0.0;
  double dx_px = 0.0;
  double dy_px = 0.0;
};

// ---- transforms.json ----

// One slice of the stack: its drift `rigid` (output point q -> observed point p, above) and
// what registration decided about it.
struct SliceTransform {
  int index = 0;     // position in the stack (0-based)
  int number = 0;    // the number parsed from the file name
  std::string file;  // the colour slice's file name
  Rigid rigid;
  bool jump = false;                // a sudden jump between the previous slice and this one
  bool black = false;               // no signal (a lost slice)
  std::optional<int> duplicate_of;  // stack index of the slice this one duplicates
  double quality = 1.0;             // [0, 1]
  nlohmann::json extra = nlohmann::json::object();  // other per-slice keys, kept on write
};

struct StackTransforms {
  int width = 0, height = 0;                        // output (and observed RGB) grid, pixels
  std::array<double, 2> center_px{0, 0};            // ((W-1)/2, (H-1)/2)
  std::optional<int> reference_slice;               // the slice defining the output frame, if any
  std::vector<SliceTransform> slices;               // one per stack index, in order
  std::optional<Similarity> ct_to_rgb;              // CT pixel u -> output q (above)
  nlohmann::json extra = nlohmann::json::object();  // unknown keys, kept on write
};

// Reads transforms.json. Throws FormatError naming the file and key (IoError if unreadable).
StackTransforms read_transforms(const std::string& path);
// The text write_transforms writes (JSON, 2-space indent, final newline).
std::string transforms_text(const StackTransforms& transforms);
// Writes transforms.json atomically (IoError).
void write_transforms(const std::string& path, const StackTransforms& transforms);

}  // namespace vispack::pipeline

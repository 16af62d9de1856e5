// Internal: the phantom's own writer of truth/transforms.json. Not installed.
//
// Independent of the pipeline's transforms.json writer ON PURPOSE: the truth must not share code
// with what it judges, so a bug in the pipeline's writer (a sign, a key, a rounding) cannot hide
// in the truth. It writes the same convention (docs/ARCHITECTURE.md "Slice transforms"): a point
// q of the output grid appears in observed slice k at p = c + R(θ_k)(q − c) + d_k, and
// `ct_to_rgb` maps CT pixel u to q = c + s·R(φ)(u − c_ct) + e.
#pragma once

#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace vispack::phantom::detail {

struct TruthSlice {
  int index = 0, number = 0;
  std::string file;
  double dx_px = 0, dy_px = 0, rotation_deg = 0;  // the true T_k (camera offset + drift)
  bool jump = false, black = false;
  int duplicate_of = -1;  // -1: none
  double gain = 1.0;      // brightness gain of the observed slice (phantom extra)
  nlohmann::ordered_json extra = nlohmann::ordered_json::object();  // appended per-slice keys
};

struct TruthTransforms {
  int width = 0, height = 0;
  std::string frame = "ct";  // "ct": output grid defined by the CT; "slice0": by slice 0
  std::vector<TruthSlice> slices;
  bool has_ct = true;
  double ct_scale = 1, ct_rotation_deg = 0, ct_dx_px = 0, ct_dy_px = 0;
  nlohmann::ordered_json extra = nlohmann::ordered_json::object();  // appended top-level keys
};

// Writes `t` as JSON to `path` atomically (IoError). With frame "ct", "reference_slice" is null;
// with "slice0" it is 0. Numbers are rounded to 1e-6 (far below anything measured).
void write_truth_transforms(const std::string& path, const TruthTransforms& t);

}  // namespace vispack::phantom::detail

// A person's registration corrections (config register.overrides): read by the register stage's
// solve (register/solve.h) and recorded in the packed file's metadata by pack. Reads no image.
// Thread-safe: pure functions.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "vispack/pipeline/core/transform_types.h"

namespace vispack::pipeline {

// A person's correction of one slice (register.overrides).
struct SliceOverride {
  int index = 0;                   // stack index
  std::optional<Rigid> transform;  // fix T_k to this
  bool jump = false;            // a jump between the previous slice and this one: cuts pair terms
  bool exclude_anchor = false;  // this slice's CT anchor is not used
  std::string note;             // free text, copied to the report
};
// The override file:
//   { "slices": [ { "index": 12, "transform": { "rotation_deg": 0.5, "dx_px": 3, "dy_px": -1 } },
//                 { "index": 40, "jump": true }, { "index": 7, "anchor": false, "note": "..." } ] }
// ("_" keys are comments). Throws ConfigError naming the file and key on anything else, an
// index outside [0, slice_count) or a slice listed twice.
std::vector<SliceOverride> read_overrides(const std::string& path, int slice_count);
nlohmann::json to_json(const SliceOverride& o);

}  // namespace vispack::pipeline

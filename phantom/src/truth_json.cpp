#include "truth_json.h"

#include <cmath>

#include "vispack/common/atomic_file.h"

namespace vispack::phantom::detail {
namespace {

using ojson = nlohmann::ordered_json;

double tidy(double v) {
  return std::round(v * 1e6) / 1e6;
}

}  // namespace

void write_truth_transforms(const std::string& path, const TruthTransforms& t) {
  ojson out;
  out["width"] = t.width;
  out["height"] = t.height;
  out["center_px"] = {(t.width - 1) * 0.5, (t.height - 1) * 0.5};
  out["frame"] = t.frame;
  out["reference_slice"] = t.frame == "slice0" ? ojson(0) : ojson(nullptr);
  ojson slices = ojson::array();
  for (const TruthSlice& s : t.slices) {
    ojson j;
    j["index"] = s.index;
    j["number"] = s.number;
    j["file"] = s.file;
    j["dx_px"] = tidy(s.dx_px);
    j["dy_px"] = tidy(s.dy_px);
    j["rotation_deg"] = tidy(s.rotation_deg);
    j["jump"] = s.jump;
    j["black"] = s.black;
    j["duplicate_of"] = s.duplicate_of >= 0 ? ojson(s.duplicate_of) : ojson(nullptr);
    j["quality"] = 1.0;
    j["gain"] = tidy(s.gain);
    for (auto it = s.extra.begin(); it != s.extra.end(); ++it)
      j[it.key()] = it.value();
    slices.push_back(j);
  }
  out["slices"] = slices;
  if (t.has_ct) {
    out["ct_to_rgb"] = {{"scale", tidy(t.ct_scale)},
                        {"rotation_deg", tidy(t.ct_rotation_deg)},
                        {"dx_px", tidy(t.ct_dx_px)},
                        {"dy_px", tidy(t.ct_dy_px)}};
  }
  for (auto it = t.extra.begin(); it != t.extra.end(); ++it)
    out[it.key()] = it.value();
  write_file_atomic(path, out.dump(2) + "\n");
}

}  // namespace vispack::phantom::detail

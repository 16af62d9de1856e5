// defined_ct_to_rgb (output_frame.h).
#include "vispack/pipeline/core/output_frame.h"

#include "vispack/common/error.h"

namespace vispack::pipeline {

Similarity defined_ct_to_rgb(const Config& config) {
  if (!config.ct) throw ConfigError(cat(config.path, ": the output frame needs a \"ct\" section"));
  const auto& f = config.registration.output_frame;
  return {config.ct->pixel_spacing_mm[0] / config.spacing_mm[0], f.rotation_deg, f.dx_px, f.dy_px};
}

}  // namespace vispack::pipeline

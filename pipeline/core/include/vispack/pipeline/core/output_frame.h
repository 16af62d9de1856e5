// The output frame the config defines: where the CT lies on the output grid before any
// registration (docs/ARCHITECTURE.md "Slice transforms"). Thread-safe: pure functions.
#pragma once

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/transform_types.h"

namespace vispack::pipeline {

// ct_to_rgb as the config defines it: scale = ct.pixel_spacing_mm[0] / spacing_mm[0], rotation
// and shift from register.output_frame. Throws ConfigError when the config has no CT.
Similarity defined_ct_to_rgb(const Config& config);

}  // namespace vispack::pipeline

// Test helper: a VolumeData (rgba, ct and labels, all present) written as a packed file.
#pragma once

#include <string>

#include <nlohmann/json.hpp>

#include "vispack/format/writer.h"
#include "vispack/render/volume.h"

namespace vispack::test {

// Writes `v` (rgba, ct and labels, all present) as a packed file with bricks of `brick_edge`
// and `extra` metadata.
inline void write_packed_volume(const std::string& path, const render::VolumeData& v,
                                int brick_edge,
                                const nlohmann::json& extra = nlohmann::json::object()) {
  format::WriterOptions o;
  o.dims = v.geometry.dims;
  o.spacing_mm = {v.geometry.spacing_mm.x, v.geometry.spacing_mm.y, v.geometry.spacing_mm.z};
  o.origin_mm = {v.geometry.origin_mm.x, v.geometry.origin_mm.y, v.geometry.origin_mm.z};
  o.brick_edge = brick_edge;
  o.threads = 1;
  o.channels = {{"rgba", format::ChannelType::kRgba8},
                {"ct", format::ChannelType::kInt16},
                {"labels", format::ChannelType::kUint16}};
  for (const render::Label& l : v.label_table)
    o.label_table.push_back({l.id, l.name, l.colour});
  o.extra_metadata = extra;
  format::write_volume(path, o, {v.rgba.data(), v.ct.data(), v.labels.data()});
}

}  // namespace vispack::test

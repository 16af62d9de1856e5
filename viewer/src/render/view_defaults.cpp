#include "vispack/render/view_defaults.h"

namespace vispack::render {

ModeDefaults mode_defaults(Mode mode) {
  ModeDefaults d;
  switch (mode) {
    case Mode::kColour:
    case Mode::kLabels:
      d.cut_away = true;
      // Opaque from the first sample in: 4 slices per voxel keep the foreground PSNR against the
      // CPU reference above 40 dB (docs/BENCHMARKS.md "Viewer defaults").
      d.slices_per_voxel = 4.0;
      break;
    case Mode::kCt:
      // Bone from 200 HU up; skin, fat, muscle and organs (−100..60 HU), gel and air stay out.
      d.window_center_hu = 600.0;
      d.window_width_hu = 800.0;
      d.slices_per_voxel = 3.0;
      break;
    case Mode::kTf2d:
      d.tf2d = {Tf2dWidget{}};
      break;
    case Mode::kMip:
    case Mode::kAverage:
    case Mode::kIso:
    case Mode::kMpr:
      break;
  }
  return d;
}

ClipPlane cut_away_plane(const Box3& box) {
  ClipPlane p;
  p.normal = {0, 1, 0};
  p.d = box.valid() ? box.centre().y : 0.0;
  return p;
}

}  // namespace vispack::render

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
      // Labels shaded by the CT (--label-shading): a soft-tissue window, fat dark, bone bright.
      if (mode == Mode::kLabels) {
        d.window_center_hu = 0.0;
        d.window_width_hu = 400.0;
      }
      break;
    case Mode::kCt:
      // Bone from 200 HU up; skin, fat, muscle and organs (−100..60 HU), gel and air stay out.
      d.window_center_hu = 600.0;
      d.window_width_hu = 800.0;
      d.slices_per_voxel = 3.0;
      break;
    case Mode::kTf2d: {
      // Boundaries, each widget's opacity rising with the gradient magnitude: the skin (air to
      // soft tissue) as a faint shell, soft-tissue borders (fat, muscle, organs) in red, bone
      // surfaces ivory; the insides of tissues stay clear.
      Tf2dWidget skin{-900, 100, 50, 400, {0.9f, 0.75f, 0.65f, 0.12f}, true};
      Tf2dWidget soft{-150, 150, 20, 200, {0.85f, 0.3f, 0.25f, 0.35f}, true};
      Tf2dWidget bone{200, 1600, 50, 400, {0.95f, 0.9f, 0.8f, 0.8f}, true};
      d.tf2d = {skin, soft, bone};
      d.slices_per_voxel = 3.0;  // thin shells: 38.3 dB at 2 slices per voxel, 512x512
      break;
    }
    case Mode::kAverage:
      // The mean HU along a ray through the body (air, fat, soft tissue, bone): −1000..200 HU.
      d.window_center_hu = -400.0;
      d.window_width_hu = 1200.0;
      break;
    case Mode::kMip:
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

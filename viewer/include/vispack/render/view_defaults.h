// What vispack-view shows when the user asks for nothing (docs/GOALS.md §4 "Viewer defaults"):
// an oblique camera, and per mode a transfer function or a cut-away that shows the inside of
// the body instead of its skin. The command line overrides each value it names; the rest come
// from here. No GL; shared by the viewer, its tests and scripts/make-readme-pictures.sh.
#pragma once

#include <vector>

#include "vispack/render/math.h"
#include "vispack/render/slicing.h"
#include "vispack/render/transfer.h"

namespace vispack::render {

// The default orbit: from the front right (azimuth, degrees about z) and from the head side
// (elevation), so three faces of the box show (the front, the right side and slice 0).
constexpr double kDefaultAzimuthDeg = 35.0;
constexpr double kDefaultElevationDeg = 35.0;

// Per-mode defaults of the transfer function and the view.
struct ModeDefaults {
  double window_center_hu = 300.0;  // CT window (ct, mip, average; labels: the shading's t)
  double window_width_hu = 1500.0;
  double opacity = 1.0;           // opacity scale per Δ0
  double slices_per_voxel = 2.0;  // slice density: enough for 40 dB foreground PSNR against the
                                  // CPU reference (docs/BENCHMARKS.md "Viewer defaults")
  bool cut_away = false;          // remove the half of the volume nearer the default camera
  std::vector<Tf2dWidget> tf2d;   // tf2d mode: the widgets (empty for the other modes)
};

// colour, labels: cut away (photographs and labels are opaque from the skin in), 4 slices per
// voxel; ct: a window that leaves skin, fat, muscle and the holder transparent and shows bone,
// 3 slices per voxel; labels: a soft-tissue window (0:400 HU) for --label-shading; tf2d: boundary
// widgets weighted by gradient magnitude, 3 slices per voxel; average: window −400:1200 HU; mip,
// iso and mpr as before (they show the inside by construction).
ModeDefaults mode_defaults(Mode mode);

// A clip plane as RenderParams holds it: samples with dot(normal, x) > d are removed.
struct ClipPlane {
  Vec3 normal{0, 1, 0};
  double d = 0.0;
};
// The default cut-away of `box`: the coronal plane through its centre (y = centre), removing the
// half on the +y side, which faces the default camera (azimuth 0 looks along −y, camera.h).
ClipPlane cut_away_plane(const Box3& box);

}  // namespace vispack::render

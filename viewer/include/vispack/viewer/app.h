// vispack-view's logic, kept in the library so the executable is a screen of code: option
// parsing, the headless screenshot path (EGL) and the interactive window (GLFW).
#pragma once

#include <cstdint>
#include <string>

#include "vispack/common/cli.h"
#include "vispack/render/brick_tree.h"
#include "vispack/render/camera.h"
#include "vispack/render/transfer.h"
#include "vispack/render/view_defaults.h"

namespace vispack::viewer {

struct ViewOptions {
  std::string file;
  std::string screenshot;  // empty: interactive window
  int width = 512, height = 512;
  bool size_set = false;  // --size given (else the window sizes itself to the screen)
  // params.mode and what the command line set; the values it did not set follow
  // render::mode_defaults (initial_params resolves them, and the window again on a mode change).
  render::RenderParams params;
  struct Given {
    bool window = false, opacity = false, slices = false, clip = false, tf2d = false;
  } given;
  render::OrbitParams orbit;   // target is the box centre plus orbit.pan_mm
  double label_opacity = 0.5;  // alpha of every label in the colour table (per Δ0)
  int level = -1;              // >= 0: draw only this level (bricked), or this whole level
  bool whole_level = false;    // one texture per channel of one level instead of paged bricks
  double lod_pixels = 1.0;     // bricks: refine while a voxel covers more pixels than this
  std::int64_t max_gpu_mb = 2048;
  int threads = 0;
  int max_frames = 0;    // interactive: close after this many frames (0: never; smoke tests)
  bool timings = false;  // print first-frame, upload and frame times to stderr
  // Interactive: commands run in order, one per line ('#' starts a comment):
  //   azimuth DEG | elevation DEG | zoom F | mode NAME   change the view (not "moving")
  //   wait                  until the view is complete (every brick it needs is drawn)
  //   screenshot OUT.png    wait, then write the volume's part of the window (free_area:
  //                         without the panel), the size a --screenshot of the view needs
  // The window closes after the last command. For tests of the window against --screenshot.
  std::string script;
};

// Declares and parses every option (throws UsageError naming a bad value). Calls args.done().
ViewOptions parse_view_options(Args& args);

// Sets the values of `params` that `options` did not give to render::mode_defaults(params.mode):
// the CT window, opacity, slice density, 2-D transfer function and the clip plane (the mode's
// cut-away of `box`, the level-0 box, or none). The mode is params.mode.
void apply_mode_defaults(render::RenderParams& params, const ViewOptions& options,
                         const render::Box3& box);

// The render parameters vispack-view draws `source` with at first (options, the mode's
// defaults, the label colour table) and the orbit (target: the level-0 box centre).
render::RenderParams initial_params(const ViewOptions& options, const render::VolumeSource& source);
render::OrbitParams initial_orbit(const ViewOptions& options, const render::VolumeSource& source);

// A rectangle of window pixels: x to the right and y down from the window's top-left corner.
struct PixelRect {
  int x = 0, y = 0, width = 0, height = 0;
};
// The window's control panel starts docked at the left edge, this wide (window pixels), or a
// third of the window when that is narrower; full height.
constexpr int kPanelWidth = 320;
PixelRect initial_panel(int window_width, int window_height);
// The part of a width × height window that the panel leaves for the volume: the largest of the
// strips left of, right of, above and below the panel (the whole window when the panel is empty
// or outside it). The camera is fitted to this area and the volume drawn into it.
PixelRect free_area(int width, int height, const PixelRect& panel);
// The window size without --size, for a screen work area of screen_w × screen_h: 85 % of it,
// at most 1600 × 1000 and at least 640 × 480 (1280 × 800 when the screen is unknown, 0 × 0).
PixelRect default_window_size(int screen_w, int screen_h);

// The brick plan options the view options ask for (--level, --lod, --max-gpu-mb).
render::PlanOptions plan_options(const ViewOptions& options, int levels);

// Renders one frame without a display and writes options.screenshot. Returns 0.
// Throws IoError/FormatError (the file), vispack::Error (no GL context).
int run_screenshot(const ViewOptions& options);

// Opens a window and runs the interactive viewer until it is closed. Throws vispack::Error
// when no window can be opened (no display) or the viewer was built without GLFW.
int run_window(const ViewOptions& options);

}  // namespace vispack::viewer

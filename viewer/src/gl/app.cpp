#include "vispack/viewer/app.h"

#include <epoxy/gl.h>

#include <time.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <sstream>
#include <vector>

#include "vispack/common/error.h"
#include "vispack/render/brick_tree.h"
#include "vispack/render/lost_slices.h"
#include "vispack/render/volume.h"
#include "vispack/viewer/brick_cache.h"
#include "vispack/viewer/context.h"
#include "vispack/viewer/slice_renderer.h"
#include "vispack/viewer/volume_textures.h"

namespace vispack::viewer {
namespace {

std::vector<double> parse_list(const std::string& option, const std::string& text, char sep,
                               std::size_t count) {
  std::vector<double> out;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, sep)) {
    try {
      std::size_t used = 0;
      out.push_back(std::stod(item, &used));
      if (used != item.size()) throw std::invalid_argument(item);
    } catch (const std::exception&) {
      throw UsageError(
          cat(option, ": '", text, "' is not ", count, " numbers separated by '", sep, "'"));
    }
  }
  if (out.size() != count)
    throw UsageError(
        cat(option, ": '", text, "' is not ", count, " numbers separated by '", sep, "'"));
  return out;
}

// CPU seconds of the whole process (every llvmpipe and decoding thread), a load-independent
// measure of a frame's work on a shared machine.
double process_cpu_seconds() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

ViewOptions parse_view_options(Args& args) {
  ViewOptions o;
  args.describe("FILE [--screenshot OUT.png --size WxH] [--mode M] [options]",
                "Renders a packed volume with view-aligned slices. With --screenshot, renders one "
                "frame headless (EGL, no X server needed) and exits; otherwise opens a window.");
  auto shot = args.option("--screenshot", "OUT.png", "render one frame headless to a PNG");
  auto size_given = args.option(
      "--size", "WxH", "frame size in pixels (default: 512x512; a window: fitted to the screen)");
  std::string mode =
      args.option("--mode", "M", "colour|ct|mip|average|iso|labels|mpr|tf2d", "colour");
  auto az =
      args.option_double("--azimuth", "DEG", "orbit azimuth (0: looking along -y; default 35)");
  auto el = args.option_double("--elevation", "DEG",
                               "orbit elevation (+: from the head side; default 35)");
  auto dist = args.option_double("--distance", "MM", "camera distance from the target");
  auto zoom = args.option_double("--zoom", "F", "zoom factor (divides the fitted distance)");
  auto fov = args.option_double("--fov", "DEG", "vertical field of view (default 30)");
  bool ortho = args.flag("--ortho", "orthographic projection");
  auto pan = args.option("--pan", "X,Y,Z", "move camera and target by this vector (mm)");
  auto spv = args.option_double("--slices-per-voxel", "S",
                                "slice density (default: colour, labels 4; ct, tf2d 3; others 2)");
  auto opacity = args.option_double("--opacity", "A", "opacity scale per voxel (default 1)");
  std::string from = args.option("--opacity-from", "alpha|ct", "colour mode opacity", "alpha");
  auto window = args.option("--window", "CENTER:WIDTH",
                            "CT window in HU (default: ct 600:800, average -400:1200, "
                            "labels 0:400, others 300:1500)");
  std::string ramp = args.option("--ramp", "NAME", "colour ramp: grey|bone|hot", "bone");
  auto iso = args.option_double("--iso", "HU", "isosurface threshold (default 300)");
  auto highlight = args.option_int("--highlight", "ID", "label to highlight (labels mode)");
  auto label_opacity = args.option_double("--label-opacity", "A", "label opacity (default 0.5)");
  std::string shading =
      args.option("--label-shading", "flat|modulated|ramp",
                  "labels: segment colour modulated by CT/colour intensity", "flat");
  auto tf2d = args.option("--tf2d", "V0:V1:G0:G1:A",
                          "tf2d mode: one widget, HU range, gradient range (HU/mm), opacity "
                          "(default: skin, soft-tissue and bone boundaries)");
  bool jitter = args.flag("--jitter", "jitter slice positions per pixel");
  auto mpr = args.option_double("--mpr-offset", "MM", "mpr plane offset from the target");
  auto clip = args.option("--clip", "NX,NY,NZ,D|off",
                          "remove samples with n.x > D (default: colour and labels cut away the "
                          "front half, y > centre)");
  auto bg = args.option("--background", "R,G,B", "background colour in [0,1] (default black)");
  auto level = args.option_int("--level", "L", "draw only this pyramid level (default: by view)");
  bool whole = args.flag("--whole-level", "one texture per channel of one level (no paging)");
  auto lod = args.option_double("--lod", "P", "bricks: pixels per voxel before refining (1)");
  auto gpu = args.option_int("--max-gpu-mb", "MB", "GPU memory budget (default 2048)");
  auto threads = args.option_int("--threads", "N", "brick decoding threads (default: all)");
  auto max_frames = args.option_int("--max-frames", "N", "interactive: exit after N frames");
  o.timings = args.flag("--timings", "print load and frame times to stderr");
  auto script = args.option("--script", "FILE", "interactive: run these view commands, then exit");
  o.file = args.positional("FILE", "packed volume (.vpk)");
  args.done();

  if (shot) o.screenshot = *shot;
  const std::string size = size_given.value_or("512x512");
  std::size_t x = size.find('x');
  std::vector<double> wh = parse_list(
      "--size", x == std::string::npos ? size : size.substr(0, x) + "," + size.substr(x + 1), ',',
      2);
  if (!(wh[0] >= 1 && wh[0] <= 16384 && wh[1] >= 1 && wh[1] <= 16384))
    throw UsageError(cat("--size: '", size, "' must be WxH with 1..16384 pixels each"));
  o.width = int(wh[0]);
  o.height = int(wh[1]);
  o.size_set = size_given.has_value();
  auto m = render::mode_from_name(mode);
  if (!m) throw UsageError(cat("--mode: unknown mode '", mode, "'"));
  o.params.mode = *m;
  o.orbit.azimuth_deg = az.value_or(render::kDefaultAzimuthDeg);
  o.orbit.elevation_deg = el.value_or(render::kDefaultElevationDeg);
  if (dist) o.orbit.distance_mm = *dist;
  if (zoom) {
    if (!(*zoom > 0)) throw UsageError("--zoom must be > 0");
    o.orbit.zoom = *zoom;
  }
  if (fov) o.orbit.fov_y_deg = *fov;
  o.orbit.orthographic = ortho;
  if (pan) {
    auto v = parse_list("--pan", *pan, ',', 3);
    o.orbit.pan_mm = {v[0], v[1], v[2]};
  }
  if (spv) {
    if (!(*spv > 0 && *spv <= 64)) throw UsageError("--slices-per-voxel must be in (0, 64]");
    o.params.slices_per_voxel = *spv;
    o.given.slices = true;
  }
  if (opacity) {
    if (!(*opacity >= 0)) throw UsageError("--opacity must be >= 0");
    o.params.opacity = *opacity;
    o.given.opacity = true;
  }
  if (from != "alpha" && from != "ct") throw UsageError("--opacity-from must be alpha or ct");
  o.params.opacity_source =
      from == "ct" ? render::OpacitySource::kCt : render::OpacitySource::kAlpha;
  if (window) {
    auto v = parse_list("--window", *window, ':', 2);
    o.params.window_center_hu = v[0];
    o.params.window_width_hu = v[1];
    o.given.window = true;
  }
  o.params.ramp = render::make_ramp(ramp);
  if (iso) o.params.iso_hu = *iso;
  if (highlight) o.params.highlight_label = int(*highlight);
  if (label_opacity) o.label_opacity = *label_opacity;
  auto ls = render::label_shading_from_name(shading);
  if (!ls) throw UsageError(cat("--label-shading: unknown value '", shading, "'"));
  o.params.label_shading = *ls;
  if (tf2d) {
    auto v = parse_list("--tf2d", *tf2d, ':', 5);
    render::Tf2dWidget w;
    w.value_lo = v[0];
    w.value_hi = v[1];
    w.gradient_lo = v[2];
    w.gradient_hi = v[3];
    w.colour.a = float(v[4]);
    if (!(v[1] > v[0]) || !(v[3] >= v[2])) throw UsageError("--tf2d: needs V0 < V1 and G0 <= G1");
    o.params.tf2d = render::make_tf2d({w}, std::min(-1000.0, v[0]), std::max(2000.0, v[1]),
                                      std::max(400.0, v[3]));
    o.given.tf2d = true;
  }
  o.params.jitter = jitter;
  if (mpr) o.params.mpr_offset_mm = *mpr;
  if (clip) o.given.clip = true;
  if (clip && *clip != "off") {
    auto v = parse_list("--clip", *clip, ',', 4);
    o.params.clip = true;
    o.params.clip_normal = {v[0], v[1], v[2]};
    o.params.clip_d = v[3];
  }
  if (bg) {
    auto v = parse_list("--background", *bg, ',', 3);
    o.params.background = {float(v[0]), float(v[1]), float(v[2]), 1.0f};
  }
  if (level) o.level = int(*level);
  o.whole_level = whole;
  if (lod) {
    if (!(*lod > 0)) throw UsageError("--lod must be > 0");
    o.lod_pixels = *lod;
  }
  if (gpu) {
    if (*gpu <= 0) throw UsageError("--max-gpu-mb must be > 0");
    o.max_gpu_mb = *gpu;
  }
  if (threads) o.threads = int(*threads);
  if (max_frames) o.max_frames = int(*max_frames);
  if (script) o.script = *script;
  return o;
}

namespace {

// The one-texture-per-level path (--whole-level): the finest level that fits the budget.
int screenshot_whole_level(const ViewOptions& options, const render::VolumeSource& source,
                           HeadlessContext& context, std::chrono::steady_clock::time_point t_open,
                           const render::RenderParams& params, const render::Camera& camera) {
  GLint max3d = 0;
  glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &max3d);
  int levels = source.level_count();
  int level =
      options.level >= 0 ? options.level : choose_level(source, max3d, options.max_gpu_mb << 20);
  if (level >= levels)
    throw UsageError(cat("--level ", level, ": ", options.file, " has ", levels, " levels"));
  SliceRenderer renderer;
  VolumeTextures textures;
  if (options.timings && level != levels - 1) {
    // Time to first frame: the coarsest level, rendered and read back.
    textures.upload(source, levels - 1, options.threads);
    renderer.render(textures, camera, params);
    renderer.read_rgba8();
    std::fprintf(stderr, "first frame (level %d): %.3f s after open\n", levels - 1,
                 seconds_since(t_open));
  }
  UploadStats up = textures.upload(source, level, options.threads);
  // A corrupt brick is drawn as missing (zeros) and reported; the picture is still written and
  // the exit code stays 0 (docs/RELIABILITY.md).
  for (const std::string& e : up.bad_brick_errors)
    std::fprintf(stderr, "vispack-view: warning: %s; shown as missing\n", e.c_str());
  if (options.timings) {  // warm-up: llvmpipe compiles shaders at the first draw
    renderer.render(textures, camera, params);
    renderer.read_rgba8();
  }
  auto t_frame = std::chrono::steady_clock::now();
  double cpu0 = process_cpu_seconds();
  FrameInfo info = renderer.render(textures, camera, params);
  render::Image8 image = renderer.read_rgba8();
  double frame_s = seconds_since(t_frame), frame_cpu = process_cpu_seconds() - cpu0;
  render::write_png(options.screenshot, image);
  if (options.timings) {
    render::LevelGeometry g = source.level(level);
    std::fprintf(stderr,
                 "%s\nlevel %d (%lldx%lldx%lld): upload %.1f MB in %.3f s (%.1f MB/s, %lld "
                 "bricks)\nframe %dx%d mode %s: %lld slices, %.3f s (%.3f CPU s)\n",
                 context.description().c_str(), level, (long long)g.dims[0], (long long)g.dims[1],
                 (long long)g.dims[2], up.bytes / 1e6, up.seconds,
                 up.seconds > 0 ? up.bytes / 1e6 / up.seconds : 0.0, (long long)up.bricks,
                 options.width, options.height, render::mode_name(params.mode),
                 (long long)info.slices, frame_s, frame_cpu);
  }
  return 0;
}

}  // namespace

void apply_mode_defaults(render::RenderParams& params, const ViewOptions& options,
                         const render::Box3& box) {
  const render::ModeDefaults d = render::mode_defaults(params.mode);
  if (!options.given.window) {
    params.window_center_hu = d.window_center_hu;
    params.window_width_hu = d.window_width_hu;
  }
  if (!options.given.opacity) params.opacity = d.opacity;
  if (!options.given.slices) params.slices_per_voxel = d.slices_per_voxel;
  if (!options.given.tf2d && !d.tf2d.empty()) params.tf2d = render::make_tf2d(d.tf2d);
  if (!options.given.clip) {
    params.clip = d.cut_away;
    if (d.cut_away) {
      const render::ClipPlane plane = render::cut_away_plane(box);
      params.clip_normal = plane.normal;
      params.clip_d = plane.d;
    }
  }
}

render::RenderParams initial_params(const ViewOptions& options,
                                    const render::VolumeSource& source) {
  render::RenderParams params = options.params;
  const render::Box3 box = source.level(0).box();
  apply_mode_defaults(params, options, box);
  params.label_colours = render::make_label_colours(source.labels(), options.label_opacity);
  params.mpr_target = box.centre() + options.orbit.pan_mm;
  return params;
}

render::OrbitParams initial_orbit(const ViewOptions& options, const render::VolumeSource& source) {
  render::OrbitParams orbit = options.orbit;
  orbit.target = source.level(0).box().centre();
  return orbit;
}

PixelRect initial_panel(int window_width, int window_height) {
  return {0, 0, std::min(kPanelWidth, window_width / 3), window_height};
}

PixelRect free_area(int width, int height, const PixelRect& panel) {
  const int x0 = std::clamp(panel.x, 0, width), x1 = std::clamp(panel.x + panel.width, 0, width);
  const int y0 = std::clamp(panel.y, 0, height), y1 = std::clamp(panel.y + panel.height, 0, height);
  if (x1 <= x0 || y1 <= y0) return {0, 0, width, height};
  const PixelRect strips[4] = {{0, 0, x0, height},
                               {x1, 0, width - x1, height},
                               {0, 0, width, y0},
                               {0, y1, width, height - y1}};
  PixelRect best{0, 0, 0, 0};
  for (const PixelRect& r : strips)
    if (std::int64_t(r.width) * r.height > std::int64_t(best.width) * best.height) best = r;
  return best;
}

PixelRect default_window_size(int screen_w, int screen_h) {
  if (screen_w <= 0 || screen_h <= 0) return {0, 0, 1280, 800};
  return {0, 0, std::clamp(int(0.85 * screen_w), 640, 1600),
          std::clamp(int(0.85 * screen_h), 480, 1000)};
}

render::PlanOptions plan_options(const ViewOptions& options, int levels) {
  render::PlanOptions o;
  if (options.level >= 0) {
    if (options.level >= levels)
      throw UsageError(
          cat("--level ", options.level, ": ", options.file, " has ", levels, " levels"));
    o.finest_level = o.coarsest_level = options.level;
  }
  o.lod_pixels = options.lod_pixels;
  o.max_bytes = options.max_gpu_mb << 20;
  o.border = BrickCache::kBorder;
  return o;
}

int run_screenshot(const ViewOptions& options) {
  auto t_open = std::chrono::steady_clock::now();
  const double cpu_open = process_cpu_seconds();
  std::shared_ptr<const render::VolumeSource> source =
      render::fill_lost_slices(render::open_packed(options.file));
  HeadlessContext context;
  const render::RenderParams params = initial_params(options, *source);
  const render::LevelGeometry g0 = source->level(0);
  const render::OrbitParams orbit = initial_orbit(options, *source);
  render::Camera camera = render::orbit_camera(orbit, g0.box(), options.width, options.height);
  if (options.timings && !source->lost_slices().empty())
    std::fprintf(stderr, "%zu lost slices sampled across\n", source->lost_slices().size());
  if (options.whole_level)
    return screenshot_whole_level(options, *source, context, t_open, params, camera);

  const int levels = source->level_count();
  const double t_context = seconds_since(t_open);
  // The coarsest level's ranges only: nothing whose cost grows with the stack before the first
  // picture (docs/BENCHMARKS.md, 'Viewer on long files'); every level's once it is drawn.
  render::BrickTree tree(*source, render::TreeBuild::kCoarseFirst);
  const double t_tree = seconds_since(t_open);
  const unsigned channels = render::channels_for(params, tree.present_channels());
  BrickCache cache(*source, options.max_gpu_mb << 20, options.threads);
  SliceRenderer renderer;
  const double t_renderer = seconds_since(t_open);
  const render::PlanOptions popt = plan_options(options, levels);
  if (options.timings) {
    // Time to first frame: the coarsest level's bricks, rendered and read back.
    render::PlanOptions first = popt;
    first.finest_level = first.coarsest_level = levels - 1;
    render::BrickPlan plan = render::plan_bricks(tree, camera, params, first, channels);
    cache.request(plan.draw, channels);
    cache.pump(-1);
    cache.use(plan.draw);
    const double t_loaded = seconds_since(t_open);
    renderer.render_bricks(cache, tree, plan, camera, params);
    renderer.read_rgba8();
    std::fprintf(stderr,
                 "first frame (level %d): %.3f s after open, %.3f CPU s (file + context %.3f, "
                 "brick tree of the coarsest level %.3f, shaders %.3f, coarsest bricks %.3f, "
                 "frame %.3f)\n",
                 levels - 1, seconds_since(t_open), process_cpu_seconds() - cpu_open, t_context,
                 t_tree - t_context, t_renderer - t_tree, t_loaded - t_renderer,
                 seconds_since(t_open) - t_loaded);
  }
  const auto t_tree_all = std::chrono::steady_clock::now();
  tree.build_all();
  if (options.timings)
    std::fprintf(stderr, "brick tree of every level: %.3f s\n", seconds_since(t_tree_all));
  auto t_load = std::chrono::steady_clock::now();
  render::BrickPlan plan = render::plan_bricks(tree, camera, params, popt, channels);
  cache.reset_counters();
  cache.request(plan.draw, channels);
  cache.pump(-1);
  cache.use(plan.draw);
  double load_s = seconds_since(t_load);
  const BrickCacheStats& cs = cache.stats();
  for (const std::string& e : cs.bad_brick_errors)
    std::fprintf(stderr, "vispack-view: warning: %s; shown as missing\n", e.c_str());
  if (options.timings) {  // warm-up: llvmpipe compiles shaders at the first draw
    renderer.render_bricks(cache, tree, plan, camera, params);
    renderer.read_rgba8();
  }
  auto t_frame = std::chrono::steady_clock::now();
  double cpu0 = process_cpu_seconds();
  FrameInfo info = renderer.render_bricks(cache, tree, plan, camera, params);
  render::Image8 image = renderer.read_rgba8();
  double frame_s = seconds_since(t_frame), frame_cpu = process_cpu_seconds() - cpu0;
  render::write_png(options.screenshot, image);
  if (options.timings) {
    int per_level[64] = {0};
    int finest = levels - 1;
    for (const render::BrickKey& k : plan.draw) {
      per_level[k.level]++;
      finest = std::min(finest, k.level);
    }
    std::string mix;
    for (int l = 0; l < levels; ++l)
      if (per_level[l]) mix += cat(mix.empty() ? "" : ", ", per_level[l], " of level ", l);
    std::int64_t whole = 0;
    for (render::Channel c :
         {render::Channel::kRgba, render::Channel::kCt, render::Channel::kLabels})
      if (channels & render::channel_bit(c))
        whole += source->level(finest).voxels() * render::channel_bytes(c);
    std::fprintf(stderr,
                 "%s\nbricks drawn: %zu (%s); skipped empty: %lld; culled: %lld\n"
                 "uploaded %.1f MB in %.3f s (%lld brick channels; whole level %d: %.1f MB)\n"
                 "frame %dx%d mode %s: %lld slices, %lld pieces (%lld empty cells skipped), "
                 "%.3f s (%.3f CPU s)\n",
                 context.description().c_str(), plan.draw.size(), mix.c_str(),
                 (long long)plan.skipped, (long long)plan.culled, cs.uploaded_bytes / 1e6, load_s,
                 (long long)cs.uploaded_bricks, finest, whole / 1e6, options.width, options.height,
                 render::mode_name(params.mode), (long long)info.slices, (long long)info.pieces,
                 (long long)info.cells_skipped, frame_s, frame_cpu);
  }
  return 0;
}

#ifndef VISPACK_HAVE_GLFW
int run_window(const ViewOptions&) {
  throw Error("this vispack-view was built without GLFW; use --screenshot");
}
#endif

}  // namespace vispack::viewer

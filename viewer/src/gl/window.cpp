// The interactive viewer: a GLFW window (OpenGL core), the slice renderer over the GPU brick
// cache (bricks paged by view: the coarsest brick first, refined as finer bricks arrive, decoded
// on worker threads and uploaded ~10 ms per frame; coarser and at lower resolution while the
// camera moves), and a Dear ImGui panel when ImGui is available (modes, window, iso, label
// shading, the 2-D transfer function editor, segments, brick and lost-slice status).
#include <epoxy/gl.h>
// epoxy must come before GLFW (it replaces the GL headers).
#include <GLFW/glfw3.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/render/brick_tree.h"
#include "vispack/render/lost_slices.h"
#include "vispack/viewer/app.h"
#include "vispack/viewer/brick_cache.h"
#include "vispack/viewer/slice_renderer.h"
#include "vispack/viewer/volume_textures.h"

#ifdef VISPACK_HAVE_IMGUI
#include <imgui.h>
#include <imgui_impl_glfw.h>
#include <imgui_impl_opengl3.h>
#endif

namespace vispack::viewer {
namespace {

struct GlfwLibrary {
  GlfwLibrary() {
    if (!glfwInit()) throw Error("cannot initialise GLFW (no display? use --screenshot)");
  }
  ~GlfwLibrary() { glfwTerminate(); }
};

struct WindowHandle {
  GLFWwindow* window = nullptr;
  ~WindowHandle() {
    if (window) glfwDestroyWindow(window);
  }
};

double now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// Interaction state shared with the GLFW callbacks through the window user pointer.
struct State {
  render::OrbitParams orbit;
  render::RenderParams params;
  double last_x = 0, last_y = 0;
  int button = -1;
  double last_change = 0;  // time of the last camera change (for lower resolution)
  bool want_mouse = false;
};

void on_button(GLFWwindow* w, int button, int action, int) {
  auto* s = static_cast<State*>(glfwGetWindowUserPointer(w));
  if (action == GLFW_PRESS && !s->want_mouse) {
    s->button = button;
    glfwGetCursorPos(w, &s->last_x, &s->last_y);
  } else if (action == GLFW_RELEASE) {
    s->button = -1;
  }
}

void on_move(GLFWwindow* w, double x, double y) {
  auto* s = static_cast<State*>(glfwGetWindowUserPointer(w));
  if (s->button < 0) return;
  double dx = x - s->last_x, dy = y - s->last_y;
  s->last_x = x;
  s->last_y = y;
  if (s->button == GLFW_MOUSE_BUTTON_LEFT) {
    s->orbit.azimuth_deg -= 0.4 * dx;
    s->orbit.elevation_deg = std::clamp(s->orbit.elevation_deg + 0.4 * dy, -89.0, 89.0);
  } else if (s->button == GLFW_MOUSE_BUTTON_RIGHT) {
    s->orbit.zoom = std::clamp(s->orbit.zoom * std::exp(-0.01 * dy), 0.05, 50.0);
  } else {
    // Pan in the view plane, scaled by the orbit distance.
    double az = radians(s->orbit.azimuth_deg), el = radians(s->orbit.elevation_deg);
    render::Vec3 f{std::sin(az) * std::cos(el), -std::cos(az) * std::cos(el), std::sin(el)};
    render::Vec3 r = render::normalize_or(render::cross(f, {0, 0, -1}), {1, 0, 0});
    render::Vec3 u = render::cross(r, f);
    double k = 0.002 * s->orbit.fov_y_deg / s->orbit.zoom * 10;
    s->orbit.pan_mm = s->orbit.pan_mm - r * (dx * k) + u * (dy * k);
  }
  s->last_change = now();
}

void on_scroll(GLFWwindow* w, double, double dy) {
  auto* s = static_cast<State*>(glfwGetWindowUserPointer(w));
  if (s->want_mouse) return;
  s->orbit.zoom = std::clamp(s->orbit.zoom * std::pow(1.1, dy), 0.05, 50.0);
  s->last_change = now();
}

void on_key(GLFWwindow* w, int key, int, int action, int) {
  if (action != GLFW_PRESS) return;
  auto* s = static_cast<State*>(glfwGetWindowUserPointer(w));
#ifdef VISPACK_HAVE_IMGUI
  if (ImGui::GetCurrentContext() && ImGui::GetIO().WantCaptureKeyboard) return;
#endif
  if (key >= GLFW_KEY_1 && key <= GLFW_KEY_8) s->params.mode = render::Mode(key - GLFW_KEY_1);
  if (key == GLFW_KEY_J) s->params.jitter = !s->params.jitter;
  if (key == GLFW_KEY_EQUAL || key == GLFW_KEY_KP_ADD)
    s->params.slices_per_voxel = std::min(s->params.slices_per_voxel * 1.25, 16.0);
  if (key == GLFW_KEY_MINUS || key == GLFW_KEY_KP_SUBTRACT)
    s->params.slices_per_voxel = std::max(s->params.slices_per_voxel / 1.25, 0.25);
  if (key == GLFW_KEY_ESCAPE || key == GLFW_KEY_Q) glfwSetWindowShouldClose(w, 1);
  s->last_change = now();
}

// One command of a --script file (app.h).
struct Command {
  std::string verb, arg;
  int line = 0;
};

std::vector<Command> read_script(const std::string& path) {
  std::vector<Command> out;
  if (path.empty()) return out;
  std::ifstream in(path);
  if (!in) throw IoError(cat(path, ": cannot read the script"));
  std::string text;
  for (int line = 1; std::getline(in, text); ++line) {
    if (auto hash = text.find('#'); hash != std::string::npos) text.erase(hash);
    std::istringstream words(text);
    Command c;
    c.line = line;
    if (!(words >> c.verb)) continue;
    std::getline(words >> std::ws, c.arg);
    while (!c.arg.empty() && std::isspace(static_cast<unsigned char>(c.arg.back())))
      c.arg.pop_back();
    const bool needs_arg = c.verb != "wait";
    if (c.verb != "azimuth" && c.verb != "elevation" && c.verb != "zoom" && c.verb != "mode" &&
        c.verb != "wait" && c.verb != "screenshot")
      throw UsageError(cat(path, ":", line, ": unknown command '", c.verb, "'"));
    if (needs_arg && c.arg.empty())
      throw UsageError(cat(path, ":", line, ": '", c.verb, "' needs an argument"));
    if (c.verb == "mode" && !render::mode_from_name(c.arg))
      throw UsageError(cat(path, ":", line, ": unknown mode '", c.arg, "'"));
    if (c.verb == "azimuth" || c.verb == "elevation" || c.verb == "zoom") {
      try {
        std::size_t used = 0;
        (void)std::stod(c.arg, &used);
        if (used != c.arg.size()) throw std::invalid_argument(c.arg);
      } catch (const std::exception&) {
        throw UsageError(cat(path, ":", line, ": '", c.arg, "' is not a number"));
      }
    }
    out.push_back(c);
  }
  return out;
}

// The volume's part of the window's frame (`area` of a framebuffer `fh` pixels high; default
// framebuffer, after the volume and before the panel), row 0 at top.
render::Image8 read_window(const PixelRect& area, int fh) {
  const int w = area.width, h = area.height;
  render::Image8 image(w, h);
  std::vector<std::uint8_t> rows(image.rgba.size());
  glBindFramebuffer(GL_FRAMEBUFFER, 0);
  glPixelStorei(GL_PACK_ALIGNMENT, 1);
  glReadPixels(area.x, fh - area.y - h, w, h, GL_RGBA, GL_UNSIGNED_BYTE, rows.data());
  const std::size_t stride = std::size_t(w) * 4;
  for (int y = 0; y < h; ++y)
    std::memcpy(&image.rgba[std::size_t(y) * stride], &rows[std::size_t(h - 1 - y) * stride],
                stride);
  return image;
}

// Runs the script's view changes up to its next wait or screenshot (those hold until the view is
// complete: run_window takes them).
void apply_view_commands(const std::vector<Command>& script, std::size_t& next, State& state) {
  for (; next < script.size(); ++next) {
    const Command& c = script[next];
    if (c.verb == "wait" || c.verb == "screenshot") break;
    if (c.verb == "azimuth") state.orbit.azimuth_deg = std::stod(c.arg);
    if (c.verb == "elevation") state.orbit.elevation_deg = std::stod(c.arg);
    if (c.verb == "zoom") state.orbit.zoom = std::stod(c.arg);
    if (c.verb == "mode") state.params.mode = *render::mode_from_name(c.arg);
  }
}

// What one frame drew and how long it took (the panel shows it; a screenshot waits for a frame
// with nothing missing).
struct FrameResult {
  render::BrickPlan plan;
  bool moving = false;
  double render_ms = 0;
};

// One frame: the camera from the interaction state (lower resolution, fewer slices and coarser
// bricks while it moves), bricks paged by view (plan with what is resident, ask for what is
// missing, coarsest first, upload for at most ~10 ms), drawn into `area` of the window's
// framebuffer (fh pixels high), the part the panel leaves free; the camera is fitted to it.
FrameResult draw_frame(const State& state, const render::LevelGeometry& g0,
                       const render::BrickTree& tree, BrickCache& cache,
                       const render::PlanOptions& base_plan, SliceRenderer& renderer,
                       const PixelRect& area, int fh) {
  const int fw = area.width, ah = area.height;
  FrameResult out;
  out.moving = now() - state.last_change < 0.25 || state.button >= 0;
  const int scale = out.moving ? 2 : 1;
  render::RenderParams params = state.params;
  if (out.moving) params.slices_per_voxel = std::max(params.slices_per_voxel / 2, 0.5);
  render::OrbitParams orbit = state.orbit;
  orbit.target = g0.box().centre();
  params.mpr_target = orbit.target + orbit.pan_mm;
  render::Camera cam =
      render::orbit_camera(orbit, g0.box(), std::max(fw / scale, 1), std::max(ah / scale, 1));
  const unsigned channels = render::channels_for(params, tree.present_channels());
  render::PlanOptions popt = base_plan;
  if (out.moving) popt.lod_pixels *= 2;
  out.plan = render::plan_bricks(tree, cam, params, popt, channels, [&](const render::BrickKey& k) {
    return cache.resident(k, channels);
  });
  cache.request(out.plan.missing, channels);
  std::size_t bad_before = cache.stats().bad_brick_errors.size();
  cache.pump(0.010);
  for (std::size_t i = bad_before; i < cache.stats().bad_brick_errors.size(); ++i)
    std::fprintf(stderr, "vispack-view: warning: %s; shown as missing\n",
                 cache.stats().bad_brick_errors[i].c_str());
  cache.use(out.plan.draw);
  const double t0 = now();
  renderer.render_bricks(cache, tree, out.plan, cam, params);
  glClearColor(0, 0, 0, 1);
  glBindFramebuffer(GL_FRAMEBUFFER, 0);
  glClear(GL_COLOR_BUFFER_BIT);
  renderer.resolve(0, area.x, fh - area.y - ah, fw, ah);
  glFinish();
  out.render_ms = (now() - t0) * 1e3;
  return out;
}

#ifdef VISPACK_HAVE_IMGUI
// The Dear ImGui panel: its own state, and one function per section.
struct Panel {
  std::vector<render::Tf2dWidget> tf_widgets = render::mode_defaults(render::Mode::kTf2d).tf2d;
  char search[64] = "";
  float clip_offset = 0.0f;
};

// Mode, window, opacity, slices per voxel, iso value, jitter, the clip plane.
void panel_render_params(State& state, Panel& panel, const render::LevelGeometry& g0) {
  const char* modes[] = {"colour", "ct", "mip", "average", "iso", "labels", "mpr", "tf2d"};
  int mode = int(state.params.mode);
  if (ImGui::Combo("mode (1-8)", &mode, modes, 8)) state.params.mode = render::Mode(mode);
  float wc = float(state.params.window_center_hu), ww = float(state.params.window_width_hu);
  if (ImGui::SliderFloat("level (HU)", &wc, -1000, 2000)) state.params.window_center_hu = wc;
  if (ImGui::SliderFloat("window (HU)", &ww, 1, 4000)) state.params.window_width_hu = ww;
  float op = float(state.params.opacity), spv = float(state.params.slices_per_voxel);
  float iso = float(state.params.iso_hu);
  if (ImGui::SliderFloat("opacity", &op, 0, 4)) state.params.opacity = op;
  if (ImGui::SliderFloat("slices/voxel", &spv, 0.25f, 8)) state.params.slices_per_voxel = spv;
  if (ImGui::SliderFloat("iso (HU)", &iso, -1000, 2000)) state.params.iso_hu = iso;
  ImGui::Checkbox("jitter (J)", &state.params.jitter);
  ImGui::Checkbox("clip plane", &state.params.clip);
  if (state.params.clip) {
    float n[3] = {float(state.params.clip_normal.x), float(state.params.clip_normal.y),
                  float(state.params.clip_normal.z)};
    if (ImGui::SliderFloat3("clip normal", n, -1, 1))
      state.params.clip_normal = render::normalize_or({n[0], n[1], n[2]}, {1, 0, 0});
    ImGui::SliderFloat("clip offset (mm)", &panel.clip_offset, -500, 500);
    state.params.clip_d =
        render::dot(state.params.clip_normal, g0.box().centre()) + panel.clip_offset;
  }
}

// Frame time, the bricks drawn per level, skipped, culled and loading, GPU memory, lost slices.
void panel_status(const FrameResult& frame, double frame_ms, const render::BrickTree& tree,
                  const BrickCache& cache, std::int64_t max_gpu_mb,
                  const std::vector<std::int64_t>& lost) {
  const int levels = tree.levels();
  int per_level[64] = {0};
  for (const render::BrickKey& k : frame.plan.draw)
    per_level[std::min(k.level, 63)]++;
  std::string mix;
  for (int l = 0; l < levels && l < 64; ++l)
    if (per_level[l]) mix += cat(mix.empty() ? "" : " ", "L", l, ":", per_level[l]);
  const BrickCacheStats& cs = cache.stats();
  ImGui::Text("frame %.1f ms; bricks %zu (%s)", frame_ms, frame.plan.draw.size(), mix.c_str());
  ImGui::Text("skipped (empty) %lld, culled %lld, loading %zu", (long long)frame.plan.skipped,
              (long long)frame.plan.culled, frame.plan.missing.size());
  ImGui::Text("GPU %.0f / %lld MB", cs.resident_bytes / 1048576.0, (long long)max_gpu_mb);
  if (!tree.complete())  // the coarsest level is drawn until then (brick_tree.h, TreeBuild)
    ImGui::Text("brick tree of the finer levels: %.0f %%", 100.0 * tree.build_progress());
  if (!lost.empty()) {
    std::string list;
    for (std::size_t i = 0; i < lost.size() && i < 12; ++i)
      list += cat(i ? ", " : "", lost[i]);
    if (lost.size() > 12) list += ", ...";
    ImGui::TextWrapped(
        "%zu lost slices (black in the file) are shown interpolated from their "
        "neighbours (display only): z = %s",
        lost.size(), list.c_str());
  }
}

// The 2-D transfer function's widgets (HU range, gradient range, colour) and its preview.
void panel_tf2d(State& state, Panel& panel) {
  std::vector<render::Tf2dWidget>& tf_widgets = panel.tf_widgets;
  bool changed = false;
  for (std::size_t i = 0; i < tf_widgets.size(); ++i) {
    render::Tf2dWidget& w = tf_widgets[i];
    ImGui::PushID(int(i));
    float v[2] = {float(w.value_lo), float(w.value_hi)};
    float g[2] = {float(w.gradient_lo), float(w.gradient_hi)};
    float c[4] = {w.colour.r, w.colour.g, w.colour.b, w.colour.a};
    if (ImGui::DragFloat2("HU range", v, 5.0f, -1000, 3000)) {
      w.value_lo = v[0];
      w.value_hi = std::max(v[1], v[0] + 1);
      changed = true;
    }
    if (ImGui::DragFloat2("|gradient| range", g, 1.0f, 0, 400)) {
      w.gradient_lo = g[0];
      w.gradient_hi = std::max(g[1], g[0]);
      changed = true;
    }
    if (ImGui::ColorEdit4("colour, opacity", c)) {
      w.colour = {c[0], c[1], c[2], c[3]};
      changed = true;
    }
    changed |= ImGui::Checkbox("opacity rises with |gradient|", &w.gradient_weighted);
    if (ImGui::Button("remove")) {
      tf_widgets.erase(tf_widgets.begin() + std::ptrdiff_t(i));
      changed = true;
      ImGui::PopID();
      break;
    }
    ImGui::Separator();
    ImGui::PopID();
  }
  if (ImGui::Button("add widget")) {
    tf_widgets.push_back(render::Tf2dWidget{});
    changed = true;
  }
  if (changed) state.params.tf2d = render::make_tf2d(tf_widgets);
  // Preview: value to the right, gradient magnitude upwards, colour × opacity.
  ImDrawList* dl = ImGui::GetWindowDrawList();
  ImVec2 o = ImGui::GetCursorScreenPos();
  const float cw = 2.5f, ch = 2.5f;
  const render::TransferFunction2D& tf = state.params.tf2d;
  for (int j = 0; j < render::TransferFunction2D::kGradients; j += 2)
    for (int i = 0; i < render::TransferFunction2D::kValues; i += 2) {
      const render::Rgba& e =
          tf.table[std::size_t(j) * render::TransferFunction2D::kValues + std::size_t(i)];
      ImU32 col = IM_COL32(int(255 * e.r * e.a), int(255 * e.g * e.a), int(255 * e.b * e.a), 255);
      float x = o.x + cw * float(i / 2), y = o.y + ch * float(31 - j / 2);
      dl->AddRectFilled(ImVec2(x, y), ImVec2(x + cw, y + ch), col);
    }
  ImGui::Dummy(ImVec2(cw * 64, ch * 32));
  ImGui::Text("HU %.0f .. %.0f (x), |gradient| 0 .. %.0f HU/mm (y)", tf.value_min, tf.value_max,
              tf.gradient_max);
}

// The segments list with a search box; picking one highlights it in labels mode.
void panel_segments(State& state, Panel& panel, const std::vector<render::Label>& labels) {
  ImGui::InputText("search", panel.search, sizeof(panel.search));
  ImGui::BeginChild("segments", ImVec2(0, 200), true);
  if (ImGui::Selectable("(none)", state.params.highlight_label < 0))
    state.params.highlight_label = -1;
  for (const render::Label& l : labels) {
    std::string name = std::to_string(l.id) + " " + l.name;
    std::string low = name, key = panel.search;
    std::transform(low.begin(), low.end(), low.begin(), ::tolower);
    std::transform(key.begin(), key.end(), key.begin(), ::tolower);
    if (!key.empty() && low.find(key) == std::string::npos) continue;
    if (ImGui::Selectable(name.c_str(), state.params.highlight_label == int(l.id))) {
      state.params.highlight_label = int(l.id);
      state.params.mode = render::Mode::kLabels;
    }
  }
  ImGui::EndChild();
}
#endif

}  // namespace

int run_window(const ViewOptions& options) {
  std::shared_ptr<const render::VolumeSource> source =
      render::fill_lost_slices(render::open_packed(options.file));
  const std::vector<std::int64_t> lost = source->lost_slices();
  // A bad script is refused before any window opens (no display needed to say so).
  const std::vector<Command> script = read_script(options.script);
  GlfwLibrary glfw;
  glfwWindowHint(GLFW_CONTEXT_VERSION_MAJOR, 3);
  glfwWindowHint(GLFW_CONTEXT_VERSION_MINOR, 3);
  glfwWindowHint(GLFW_OPENGL_PROFILE, GLFW_OPENGL_CORE_PROFILE);
  glfwWindowHint(GLFW_OPENGL_FORWARD_COMPAT, GLFW_TRUE);
  int width = options.width, height = options.height;
  if (!options.size_set) {  // fitted to the screen: the volume beside the panel, both readable
    int sx = 0, sy = 0, sw = 0, sh = 0;
    if (GLFWmonitor* monitor = glfwGetPrimaryMonitor())
      glfwGetMonitorWorkarea(monitor, &sx, &sy, &sw, &sh);
    const PixelRect size = default_window_size(sw, sh);
    width = size.width;
    height = size.height;
  }
  WindowHandle handle;
  handle.window =
      glfwCreateWindow(width, height, ("vispack-view " + options.file).c_str(), nullptr, nullptr);
  if (!handle.window) throw Error("cannot open an OpenGL 3.3 core window (use --screenshot)");
  GLFWwindow* window = handle.window;
  glfwMakeContextCurrent(window);
  glfwSwapInterval(1);

  State state;
  state.params = initial_params(options, *source);
  state.orbit = options.orbit;
  std::vector<render::Label> labels = source->labels();
  render::LevelGeometry g0 = source->level(0);
  render::Mode shown_mode = state.params.mode;
  glfwSetWindowUserPointer(window, &state);
  glfwSetMouseButtonCallback(window, on_button);
  glfwSetCursorPosCallback(window, on_move);
  glfwSetScrollCallback(window, on_scroll);
  glfwSetKeyCallback(window, on_key);

  const int levels = source->level_count();
  // The coarsest level's ranges only; every level's are built across the frames that follow
  // (docs/BENCHMARKS.md, 'Viewer on long files').
  render::BrickTree tree(*source, render::TreeBuild::kCoarseFirst);
  BrickCache cache(*source, options.max_gpu_mb << 20, options.threads);
  const render::PlanOptions base_plan = plan_options(options, levels);
  SliceRenderer renderer;

#ifdef VISPACK_HAVE_IMGUI
  IMGUI_CHECKVERSION();
  ImGui::CreateContext();
  ImGui::GetIO().IniFilename = nullptr;  // no imgui.ini in the current directory
  struct ImGuiGuard {
    ~ImGuiGuard() {
      ImGui_ImplOpenGL3_Shutdown();
      ImGui_ImplGlfw_Shutdown();
      ImGui::DestroyContext();
    }
  };
  ImGui_ImplGlfw_InitForOpenGL(window, true);
  ImGui_ImplOpenGL3_Init("#version 330 core");
  ImGuiGuard imgui_guard;
  Panel panel;
#endif

  std::size_t next_command = 0;
  double frame_ms = 0;
  // The panel's rectangle in window pixels (as the last frame drew it; none without ImGui).
  PixelRect panel_rect{0, 0, 0, 0};
#ifdef VISPACK_HAVE_IMGUI
  panel_rect = initial_panel(width, height);
#endif
  for (int frame_index = 0; !glfwWindowShouldClose(window); ++frame_index) {
    if (options.max_frames > 0 && frame_index >= options.max_frames) break;
    glfwPollEvents();
    // Script: view changes run at once; wait/screenshot hold until the view is complete.
    apply_view_commands(script, next_command, state);
    if (!script.empty() && next_command >= script.size()) break;
    if (state.params.mode != shown_mode) {  // a new mode starts from its defaults
      apply_mode_defaults(state.params, options, g0.box());
      shown_mode = state.params.mode;
    }
    int fw = 1, fh = 1, ww = 1, wh = 1;
    glfwGetFramebufferSize(window, &fw, &fh);
    glfwGetWindowSize(window, &ww, &wh);
    // The panel in framebuffer pixels (they differ from window pixels on a high-DPI screen).
    const double kx = double(fw) / std::max(ww, 1), ky = double(fh) / std::max(wh, 1);
    const PixelRect area =
        free_area(fw, fh,
                  {int(panel_rect.x * kx), int(panel_rect.y * ky),
                   int(std::ceil(panel_rect.width * kx)), int(std::ceil(panel_rect.height * ky))});
    const FrameResult frame = draw_frame(state, g0, tree, cache, base_plan, renderer, area, fh);
    frame_ms = 0.9 * frame_ms + 0.1 * frame.render_ms;
    if (next_command < script.size() && !frame.moving && frame.plan.missing.empty() &&
        !cache.busy() && tree.complete()) {
      const Command& c = script[next_command];
      if (c.verb == "screenshot") render::write_png(c.arg, read_window(area, fh));
      ++next_command;
    }

#ifdef VISPACK_HAVE_IMGUI
    ImGui_ImplOpenGL3_NewFrame();
    ImGui_ImplGlfw_NewFrame();
    ImGui::NewFrame();
    state.want_mouse = ImGui::GetIO().WantCaptureMouse;
    const PixelRect first = initial_panel(ww, wh);
    ImGui::SetNextWindowPos(ImVec2(float(first.x), float(first.y)), ImGuiCond_FirstUseEver);
    ImGui::SetNextWindowSize(ImVec2(float(first.width), float(first.height)),
                             ImGuiCond_FirstUseEver);
    ImGui::Begin("vispack");
    {
      const ImVec2 pos = ImGui::GetWindowPos(), size = ImGui::GetWindowSize();
      panel_rect = {int(pos.x), int(pos.y), int(std::ceil(size.x)), int(std::ceil(size.y))};
    }
    panel_render_params(state, panel, g0);
    panel_status(frame, frame_ms, tree, cache, options.max_gpu_mb, lost);
    if (state.params.mode == render::Mode::kLabels) {
      const char* shadings[] = {"flat", "modulated by intensity", "ramp per segment"};
      int sh = int(state.params.label_shading);
      if (ImGui::Combo("label colour", &sh, shadings, 3))
        state.params.label_shading = render::LabelShading(sh);
    }
    if (state.params.mode == render::Mode::kTf2d &&
        ImGui::CollapsingHeader("2-D transfer function", ImGuiTreeNodeFlags_DefaultOpen))
      panel_tf2d(state, panel);
    if (!labels.empty()) panel_segments(state, panel, labels);
    ImGui::End();
    ImGui::Render();
    ImGui_ImplOpenGL3_RenderDrawData(ImGui::GetDrawData());
#endif
    glfwSwapBuffers(window);
    // The finer levels' ranges, a slice of time per frame (more while the view rests).
    if (!tree.complete()) tree.build_for(frame.moving ? 0.03 : 0.25);
  }
  return 0;
}

}  // namespace vispack::viewer

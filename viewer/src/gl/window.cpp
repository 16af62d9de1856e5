// The interactive viewer: a GLFW window (OpenGL core), the slice renderer, progressive loading
// (coarsest level first, then the finest level that fits, brick by brick between frames),
// lower resolution while the camera moves, and a Dear ImGui panel when ImGui is available.
#include <epoxy/gl.h>
// epoxy must come before GLFW (it replaces the GL headers).
#include <GLFW/glfw3.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>

#include "vispack/common/error.h"
#include "vispack/viewer/app.h"
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
    double az = s->orbit.azimuth_deg * M_PI / 180, el = s->orbit.elevation_deg * M_PI / 180;
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
  if (key >= GLFW_KEY_1 && key <= GLFW_KEY_7) s->params.mode = render::Mode(key - GLFW_KEY_1);
  if (key == GLFW_KEY_J) s->params.jitter = !s->params.jitter;
  if (key == GLFW_KEY_EQUAL || key == GLFW_KEY_KP_ADD)
    s->params.slices_per_voxel = std::min(s->params.slices_per_voxel * 1.25, 16.0);
  if (key == GLFW_KEY_MINUS || key == GLFW_KEY_KP_SUBTRACT)
    s->params.slices_per_voxel = std::max(s->params.slices_per_voxel / 1.25, 0.25);
  if (key == GLFW_KEY_ESCAPE || key == GLFW_KEY_Q) glfwSetWindowShouldClose(w, 1);
  s->last_change = now();
}

}  // namespace

int run_window(const ViewOptions& options) {
  std::unique_ptr<render::VolumeSource> source = render::open_packed(options.file);
  GlfwLibrary glfw;
  glfwWindowHint(GLFW_CONTEXT_VERSION_MAJOR, 3);
  glfwWindowHint(GLFW_CONTEXT_VERSION_MINOR, 3);
  glfwWindowHint(GLFW_OPENGL_PROFILE, GLFW_OPENGL_CORE_PROFILE);
  glfwWindowHint(GLFW_OPENGL_FORWARD_COMPAT, GLFW_TRUE);
  WindowHandle handle;
  handle.window = glfwCreateWindow(options.width, options.height,
                                   ("vispack-view " + options.file).c_str(), nullptr, nullptr);
  if (!handle.window) throw Error("cannot open an OpenGL 3.3 core window (use --screenshot)");
  GLFWwindow* window = handle.window;
  glfwMakeContextCurrent(window);
  glfwSwapInterval(1);

  State state;
  state.params = options.params;
  state.orbit = options.orbit;
  state.params.label_colours = render::make_label_colours(source->labels(), options.label_opacity);
  std::vector<render::Label> labels = source->labels();
  render::LevelGeometry g0 = source->level(0);
  glfwSetWindowUserPointer(window, &state);
  glfwSetMouseButtonCallback(window, on_button);
  glfwSetCursorPosCallback(window, on_move);
  glfwSetScrollCallback(window, on_scroll);
  glfwSetKeyCallback(window, on_key);

  GLint max3d = 0;
  glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &max3d);
  int levels = source->level_count();
  int target_level = options.level >= 0 ? std::min(options.level, levels - 1)
                                        : choose_level(*source, max3d, options.max_gpu_mb << 20);
  SliceRenderer renderer;
  // Coarsest level first: the first frame appears at once; the finest level streams in.
  auto current = std::make_unique<VolumeTextures>();
  current->upload(*source, levels - 1, options.threads);
  std::unique_ptr<VolumeTextures> loading;
  if (target_level != levels - 1) {
    loading = std::make_unique<VolumeTextures>();
    loading->begin(*source, target_level, options.threads);
  }

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
  char search[64] = "";
  float clip_offset = 0.0f;
#endif

  double frame_ms = 0;
  for (int frame = 0; !glfwWindowShouldClose(window); ++frame) {
    if (options.max_frames > 0 && frame >= options.max_frames) break;
    glfwPollEvents();
    if (loading && loading->pump(0.010)) {  // at most ~10 ms of uploads per frame
      for (const std::string& e : loading->stats().bad_brick_errors)
        std::fprintf(stderr, "vispack-view: warning: %s; shown as missing\n", e.c_str());
      current = std::move(loading);
      state.last_change = now();
    }
    int fw = 1, fh = 1;
    glfwGetFramebufferSize(window, &fw, &fh);
    bool moving = now() - state.last_change < 0.25 || state.button >= 0;
    // Lower resolution and fewer slices while the camera moves; full quality when it stops.
    int scale = moving ? 2 : 1;
    render::RenderParams params = state.params;
    if (moving) params.slices_per_voxel = std::max(params.slices_per_voxel / 2, 0.5);
    render::OrbitParams orbit = state.orbit;
    orbit.target = g0.box().centre();
    params.mpr_target = orbit.target + orbit.pan_mm;
    render::Camera cam =
        render::orbit_camera(orbit, g0.box(), std::max(fw / scale, 1), std::max(fh / scale, 1));
    double t0 = now();
    renderer.render(*current, cam, params);
    glClearColor(0, 0, 0, 1);
    glBindFramebuffer(GL_FRAMEBUFFER, 0);
    glClear(GL_COLOR_BUFFER_BIT);
    renderer.resolve(0, 0, 0, fw, fh);
    glFinish();
    frame_ms = 0.9 * frame_ms + 0.1 * (now() - t0) * 1e3;

#ifdef VISPACK_HAVE_IMGUI
    ImGui_ImplOpenGL3_NewFrame();
    ImGui_ImplGlfw_NewFrame();
    ImGui::NewFrame();
    state.want_mouse = ImGui::GetIO().WantCaptureMouse;
    ImGui::Begin("vispack");
    const char* modes[] = {"colour", "ct", "mip", "average", "iso", "labels", "mpr"};
    int mode = int(state.params.mode);
    if (ImGui::Combo("mode (1-7)", &mode, modes, 7)) state.params.mode = render::Mode(mode);
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
      ImGui::SliderFloat("clip offset (mm)", &clip_offset, -500, 500);
      state.params.clip_d = render::dot(state.params.clip_normal, g0.box().centre()) + clip_offset;
    }
    ImGui::Text("frame %.1f ms, level %d%s", frame_ms, current->level(),
                loading ? " (loading finer level)" : "");
    if (!labels.empty()) {
      ImGui::InputText("search", search, sizeof(search));
      ImGui::BeginChild("segments", ImVec2(0, 200), true);
      if (ImGui::Selectable("(none)", state.params.highlight_label < 0))
        state.params.highlight_label = -1;
      for (const render::Label& l : labels) {
        std::string name = std::to_string(l.id) + " " + l.name;
        std::string low = name, key = search;
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
    ImGui::End();
    ImGui::Render();
    ImGui_ImplOpenGL3_RenderDrawData(ImGui::GetDrawData());
#endif
    glfwSwapBuffers(window);
  }
  return 0;
}

}  // namespace vispack::viewer

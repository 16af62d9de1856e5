// OpenGL contexts: a headless one (EGL, no X server, no window) for screenshots and tests, and
// a GLFW window for the interactive viewer.
//
// Headless platform order: the environment variable VISPACK_EGL_PLATFORM ("device",
// "surfaceless" or "default") forces one; otherwise EGL devices that are not software
// renderers are tried first (GPU servers without a display), then Mesa's surfaceless platform
// (llvmpipe in CI), then any EGL device, then the default display (X11/Wayland). The context
// is OpenGL 4.5, 4.3 or 3.3 core, made current without a surface; rendering goes to
// framebuffer objects.
#pragma once

#include <memory>
#include <string>

namespace vispack::viewer {

class HeadlessContext {
 public:
  // Creates the context and makes it current on the calling thread. Throws vispack::Error
  // with every platform's failure when none works.
  HeadlessContext();
  ~HeadlessContext();
  HeadlessContext(const HeadlessContext&) = delete;
  HeadlessContext& operator=(const HeadlessContext&) = delete;
  // "EGL surfaceless: llvmpipe (LLVM 15...), 4.5 (Core Profile) Mesa 22.3.6".
  const std::string& description() const { return description_; }

  struct Impl;  // EGL display and context (defined in context.cpp)

 private:
  std::unique_ptr<Impl> impl_;
  std::string description_;
};

// GL renderer and version strings of the current context.
std::string gl_description();

}  // namespace vispack::viewer

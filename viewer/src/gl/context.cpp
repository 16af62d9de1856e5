#include "vispack/viewer/context.h"

#include <epoxy/egl.h>
#include <epoxy/gl.h>

#include <cstdlib>
#include <cstring>
#include <vector>

#include "vispack/common/error.h"

namespace vispack::viewer {

std::string gl_description() {
  auto str = [](GLenum e) {
    const GLubyte* s = glGetString(e);
    return s ? std::string(reinterpret_cast<const char*>(s)) : std::string("?");
  };
  return cat(str(GL_RENDERER), ", ", str(GL_VERSION));
}

struct HeadlessContext::Impl {
  EGLDisplay display = EGL_NO_DISPLAY;
  EGLContext context = EGL_NO_CONTEXT;
  ~Impl() {
    if (display != EGL_NO_DISPLAY) {
      eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
      if (context != EGL_NO_CONTEXT) eglDestroyContext(display, context);
      eglTerminate(display);
    }
  }
};

namespace {

bool has_extension(const char* list, const char* name) {
  if (!list) return false;
  std::size_t n = std::strlen(name);
  for (const char* p = list; (p = std::strstr(p, name)) != nullptr; p += n)
    if ((p == list || p[-1] == ' ') && (p[n] == ' ' || p[n] == '\0')) return true;
  return false;
}

// Initialises `display` and creates a current core context on it; false (with `why`) if not.
bool try_display(EGLDisplay display, HeadlessContext::Impl& impl, std::string& why) {
  if (display == EGL_NO_DISPLAY) {
    why = "no display";
    return false;
  }
  EGLint major = 0, minor = 0;
  if (!eglInitialize(display, &major, &minor)) {
    why = cat("eglInitialize failed (0x", std::hex, eglGetError(), ")");
    return false;
  }
  impl.display = display;
  if (!eglBindAPI(EGL_OPENGL_API)) {
    why = "eglBindAPI(EGL_OPENGL_API) failed";
    return false;
  }
  const char* ext = eglQueryString(display, EGL_EXTENSIONS);
  EGLConfig config = nullptr;
  EGLint count = 0;
  const EGLint config_attribs[] = {EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_NONE};
  eglChooseConfig(display, config_attribs, &config, 1, &count);
  if (count == 0 && !has_extension(ext, "EGL_KHR_no_config_context")) {
    why = "no OpenGL config and no EGL_KHR_no_config_context";
    return false;
  }
  const int versions[][2] = {{4, 5}, {4, 3}, {3, 3}};
  for (const auto& v : versions) {
    const EGLint attribs[] = {EGL_CONTEXT_MAJOR_VERSION,
                              v[0],
                              EGL_CONTEXT_MINOR_VERSION,
                              v[1],
                              EGL_CONTEXT_OPENGL_PROFILE_MASK,
                              EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT,
                              EGL_NONE};
    impl.context =
        eglCreateContext(display, count ? config : EGL_NO_CONFIG_KHR, EGL_NO_CONTEXT, attribs);
    if (impl.context != EGL_NO_CONTEXT) break;
  }
  if (impl.context == EGL_NO_CONTEXT) {
    why = cat("eglCreateContext failed (0x", std::hex, eglGetError(), ")");
    return false;
  }
  if (!eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, impl.context)) {
    why = cat("eglMakeCurrent without a surface failed (0x", std::hex, eglGetError(), ")");
    return false;
  }
  return true;
}

void release(HeadlessContext::Impl& impl) {
  if (impl.display != EGL_NO_DISPLAY) {
    eglMakeCurrent(impl.display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
    if (impl.context != EGL_NO_CONTEXT) eglDestroyContext(impl.display, impl.context);
    eglTerminate(impl.display);
  }
  impl.display = EGL_NO_DISPLAY;
  impl.context = EGL_NO_CONTEXT;
}

}  // namespace

HeadlessContext::HeadlessContext() : impl_(std::make_unique<Impl>()) {
  const char* client = eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS);
  const char* forced = std::getenv("VISPACK_EGL_PLATFORM");
  std::string want = forced ? forced : "";
  std::vector<std::string> errors;
  auto attempt = [&](const std::string& label, EGLDisplay display) {
    std::string why;
    if (try_display(display, *impl_, why)) {
      description_ = cat("EGL ", label, ": ", gl_description());
      return true;
    }
    release(*impl_);
    errors.push_back(cat(label, ": ", why));
    return false;
  };

  bool platform_base = has_extension(client, "EGL_EXT_platform_base");
  // EGL devices (GPU servers without a display). Software devices are kept for later.
  std::vector<EGLDeviceEXT> hardware, software;
  if (platform_base && has_extension(client, "EGL_EXT_device_enumeration") &&
      has_extension(client, "EGL_EXT_platform_device") && (want.empty() || want == "device")) {
    EGLDeviceEXT devices[16];
    EGLint n = 0;
    if (eglQueryDevicesEXT(16, devices, &n))
      for (EGLint i = 0; i < n; ++i) {
        const char* dext = eglQueryDeviceStringEXT(devices[i], EGL_EXTENSIONS);
        (has_extension(dext, "EGL_MESA_device_software") ? software : hardware)
            .push_back(devices[i]);
      }
  }
  for (std::size_t i = 0; i < hardware.size(); ++i)
    if (attempt(cat("device ", i),
                eglGetPlatformDisplayEXT(EGL_PLATFORM_DEVICE_EXT, hardware[i], nullptr)))
      return;
  if (platform_base && has_extension(client, "EGL_MESA_platform_surfaceless") &&
      (want.empty() || want == "surfaceless"))
    if (attempt("surfaceless", eglGetPlatformDisplayEXT(EGL_PLATFORM_SURFACELESS_MESA,
                                                        EGL_DEFAULT_DISPLAY, nullptr)))
      return;
  for (std::size_t i = 0; i < software.size(); ++i)
    if (attempt(cat("software device ", i),
                eglGetPlatformDisplayEXT(EGL_PLATFORM_DEVICE_EXT, software[i], nullptr)))
      return;
  if (want.empty() || want == "default")
    if (attempt("default display", eglGetDisplay(EGL_DEFAULT_DISPLAY))) return;
  std::string all;
  for (const std::string& e : errors)
    all += (all.empty() ? "" : "; ") + e;
  if (all.empty()) all = cat("no EGL platform matches VISPACK_EGL_PLATFORM=", want);
  throw Error(cat("cannot create a headless OpenGL context (", all, ")"));
}

HeadlessContext::~HeadlessContext() = default;

}  // namespace vispack::viewer

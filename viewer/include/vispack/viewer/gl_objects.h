// RAII wrappers of OpenGL objects. Each owns one GL name, deletes it in its destructor, and is
// movable but not copyable. All of them require a current GL context (libepoxy loads the entry
// points) on the calling thread, at construction and destruction alike.
#pragma once

#include <epoxy/gl.h>

#include <string>
#include <utility>

namespace vispack::viewer {

template <void (*Delete)(GLuint)>
class GlName {
 public:
  GlName() = default;
  explicit GlName(GLuint id) : id_(id) {}
  ~GlName() { reset(); }
  GlName(GlName&& o) noexcept : id_(std::exchange(o.id_, 0)) {}
  GlName& operator=(GlName&& o) noexcept {
    if (this != &o) {
      reset();
      id_ = std::exchange(o.id_, 0);
    }
    return *this;
  }
  GlName(const GlName&) = delete;
  GlName& operator=(const GlName&) = delete;
  GLuint id() const { return id_; }
  explicit operator bool() const { return id_ != 0; }
  void reset() {
    if (id_) Delete(id_);
    id_ = 0;
  }

 private:
  GLuint id_ = 0;
};

namespace detail {
inline void delete_texture(GLuint id) {
  glDeleteTextures(1, &id);
}
inline void delete_buffer(GLuint id) {
  glDeleteBuffers(1, &id);
}
inline void delete_vertex_array(GLuint id) {
  glDeleteVertexArrays(1, &id);
}
inline void delete_framebuffer(GLuint id) {
  glDeleteFramebuffers(1, &id);
}
inline void delete_program(GLuint id) {
  glDeleteProgram(id);
}
}  // namespace detail

using Texture = GlName<detail::delete_texture>;
using Buffer = GlName<detail::delete_buffer>;
using VertexArray = GlName<detail::delete_vertex_array>;
using Framebuffer = GlName<detail::delete_framebuffer>;
using Program = GlName<detail::delete_program>;

Texture make_texture();
Buffer make_buffer();
VertexArray make_vertex_array();
Framebuffer make_framebuffer();

// Compiles and links a vertex + fragment shader pair. Throws vispack::Error with the driver's
// info log and `name` when compiling or linking fails.
Program make_program(const std::string& name, const std::string& vertex_source,
                     const std::string& fragment_source);

// Throws vispack::Error naming `where` if glGetError() reports an error (and drains the queue).
void check_gl(const char* where);

}  // namespace vispack::viewer

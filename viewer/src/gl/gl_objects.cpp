#include "vispack/viewer/gl_objects.h"

#include <vector>

#include "vispack/common/error.h"

namespace vispack::viewer {

Texture make_texture() {
  GLuint id = 0;
  glGenTextures(1, &id);
  return Texture(id);
}
Buffer make_buffer() {
  GLuint id = 0;
  glGenBuffers(1, &id);
  return Buffer(id);
}
VertexArray make_vertex_array() {
  GLuint id = 0;
  glGenVertexArrays(1, &id);
  return VertexArray(id);
}
Framebuffer make_framebuffer() {
  GLuint id = 0;
  glGenFramebuffers(1, &id);
  return Framebuffer(id);
}

namespace {
struct Shader {
  GLuint id;
  ~Shader() { glDeleteShader(id); }
};
GLuint compile(const std::string& name, GLenum type, const std::string& source) {
  GLuint id = glCreateShader(type);
  const char* text = source.c_str();
  glShaderSource(id, 1, &text, nullptr);
  glCompileShader(id);
  GLint ok = 0;
  glGetShaderiv(id, GL_COMPILE_STATUS, &ok);
  if (!ok) {
    GLint len = 0;
    glGetShaderiv(id, GL_INFO_LOG_LENGTH, &len);
    std::vector<char> log(std::size_t(len > 0 ? len : 1), '\0');
    glGetShaderInfoLog(id, GLsizei(log.size()), nullptr, log.data());
    glDeleteShader(id);
    throw Error(cat("shader '", name, "' (", type == GL_VERTEX_SHADER ? "vertex" : "fragment",
                    ") does not compile: ", log.data()));
  }
  return id;
}
}  // namespace

Program make_program(const std::string& name, const std::string& vertex_source,
                     const std::string& fragment_source) {
  Shader vs{compile(name, GL_VERTEX_SHADER, vertex_source)};
  Shader fs{compile(name, GL_FRAGMENT_SHADER, fragment_source)};
  Program program(glCreateProgram());
  glAttachShader(program.id(), vs.id);
  glAttachShader(program.id(), fs.id);
  glLinkProgram(program.id());
  GLint ok = 0;
  glGetProgramiv(program.id(), GL_LINK_STATUS, &ok);
  if (!ok) {
    GLint len = 0;
    glGetProgramiv(program.id(), GL_INFO_LOG_LENGTH, &len);
    std::vector<char> log(std::size_t(len > 0 ? len : 1), '\0');
    glGetProgramInfoLog(program.id(), GLsizei(log.size()), nullptr, log.data());
    throw Error(cat("shader program '", name, "' does not link: ", log.data()));
  }
  return program;
}

void check_gl(const char* where) {
  GLenum first = glGetError();
  if (first == GL_NO_ERROR) return;
  for (int i = 0; i < 32 && glGetError() != GL_NO_ERROR; ++i) {
  }
  throw Error(cat("OpenGL error 0x", std::hex, first, " in ", where));
}

}  // namespace vispack::viewer

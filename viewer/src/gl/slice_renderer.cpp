#include "vispack/viewer/slice_renderer.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <vector>

#include "shaders.h"
#include "vispack/common/error.h"
#include "vispack/render/reference.h"
#include "vispack/render/slicing.h"

namespace vispack::viewer {

using render::Channel;
using render::Mode;

struct SliceRenderer::Impl {
  Program slice_program, resolve_program;
  VertexArray vao, empty_vao;
  Buffer vbo;
  Texture ramp, label_colours;
  Texture acc_texture, out_texture;
  Framebuffer acc_fbo, out_fbo;
  int width = 0, height = 0, out_width = 0, out_height = 0;
  std::vector<render::Rgba> ramp_data, label_data;  // last uploaded
  render::RenderParams last;
  std::vector<float> vertices;

  GLint loc(GLuint program, const char* name) { return glGetUniformLocation(program, name); }

  void ensure_targets(int w, int h) {
    if (w == width && h == height && acc_texture) return;
    acc_texture = make_texture();
    glBindTexture(GL_TEXTURE_2D, acc_texture.id());
    glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA32F, w, h, 0, GL_RGBA, GL_FLOAT, nullptr);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    acc_fbo = make_framebuffer();
    glBindFramebuffer(GL_FRAMEBUFFER, acc_fbo.id());
    glFramebufferTexture2D(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_TEXTURE_2D, acc_texture.id(),
                           0);
    if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
      throw Error(cat("RGBA32F accumulation framebuffer ", w, "x", h, " is incomplete"));
    width = w;
    height = h;
    check_gl("creating the accumulation buffer");
  }

  void upload_tables(const render::RenderParams& p) {
    std::vector<render::Rgba> r(p.ramp.begin(), p.ramp.end());
    if (r.size() != ramp_data.size() ||
        std::memcmp(r.data(), ramp_data.data(), r.size() * sizeof(render::Rgba)) != 0) {
      glBindTexture(GL_TEXTURE_2D, ramp.id());
      glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA32F, render::kRampSize, 1, 0, GL_RGBA, GL_FLOAT,
                   r.data());
      ramp_data = std::move(r);
    }
    std::vector<render::Rgba> l = p.label_colours;
    l.resize(render::kLabelTableSize, render::Rgba{0.5f, 0.5f, 0.5f, 1.0f});
    l[0] = render::Rgba{};
    if (l.size() != label_data.size() ||
        std::memcmp(l.data(), label_data.data(), l.size() * sizeof(render::Rgba)) != 0) {
      glBindTexture(GL_TEXTURE_2D, label_colours.id());
      glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA32F, 256, 256, 0, GL_RGBA, GL_FLOAT, l.data());
      label_data = std::move(l);
    }
  }
};

SliceRenderer::SliceRenderer() : impl_(std::make_unique<Impl>()) {
  Impl& s = *impl_;
  s.slice_program = make_program("slice", shaders::kSliceVertex, shaders::kSliceFragment);
  s.resolve_program = make_program("resolve", shaders::kResolveVertex, shaders::kResolveFragment);
  s.vao = make_vertex_array();
  s.empty_vao = make_vertex_array();
  s.vbo = make_buffer();
  glBindVertexArray(s.vao.id());
  glBindBuffer(GL_ARRAY_BUFFER, s.vbo.id());
  glEnableVertexAttribArray(0);
  glVertexAttribPointer(0, 3, GL_FLOAT, GL_FALSE, 3 * sizeof(float), nullptr);
  glBindVertexArray(0);
  for (Texture* t : {&s.ramp, &s.label_colours}) {
    *t = make_texture();
    glBindTexture(GL_TEXTURE_2D, t->id());
    bool linear = t == &s.ramp;
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, linear ? GL_LINEAR : GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, linear ? GL_LINEAR : GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_S, GL_CLAMP_TO_EDGE);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_T, GL_CLAMP_TO_EDGE);
  }
  check_gl("creating the slice renderer");
}

SliceRenderer::~SliceRenderer() = default;

FrameInfo SliceRenderer::render(const VolumeTextures& volume, const render::Camera& cam,
                                const render::RenderParams& params) {
  Impl& s = *impl_;
  FrameInfo info;
  s.ensure_targets(std::max(cam.width, 1), std::max(cam.height, 1));
  s.upload_tables(params);
  s.last = params;
  const render::LevelGeometry& g = volume.geometry();
  render::Box3 box = g.box();

  // Proxy geometry on the world-fixed lattice (back to front), or the single MPR plane.
  double delta = render::slice_spacing(cam, g, params.slices_per_voxel);
  double near_d = render::dot(cam.forward, cam.eye) + cam.near_mm;
  std::vector<render::Vec3> tris;
  if (params.mode == Mode::kMpr) {
    double d = render::dot(cam.forward, params.mpr_target + cam.forward * params.mpr_offset_mm);
    if (d > near_d) {
      std::vector<render::Vec3> poly = render::slice_polygon(box, cam.forward, d);
      for (std::size_t j = 1; j + 1 < poly.size(); ++j)
        tris.insert(tris.end(), {poly[0], poly[j], poly[j + 1]});
      info.slices = poly.empty() ? 0 : 1;
    }
  } else {
    render::SliceLattice lat = render::slice_lattice(box, cam.forward, delta, near_d);
    tris = render::slice_triangles(box, lat, true);
    info.slices = lat.count;
  }
  info.triangles = std::int64_t(tris.size() / 3);
  info.slice_spacing_mm = delta;
  s.vertices.resize(tris.size() * 3);
  for (std::size_t i = 0; i < tris.size(); ++i) {
    s.vertices[3 * i] = float(tris[i].x);
    s.vertices[3 * i + 1] = float(tris[i].y);
    s.vertices[3 * i + 2] = float(tris[i].z);
  }

  glBindFramebuffer(GL_FRAMEBUFFER, s.acc_fbo.id());
  glViewport(0, 0, s.width, s.height);
  glDisable(GL_DEPTH_TEST);
  glDisable(GL_CULL_FACE);
  if (params.mode == Mode::kMip)
    glClearColor(-1e30f, 0, 0, 0);
  else
    glClearColor(0, 0, 0, 0);
  glClear(GL_COLOR_BUFFER_BIT);
  if (s.vertices.empty()) {
    check_gl("rendering an empty frame");
    return info;
  }

  glEnable(GL_BLEND);
  if (params.mode == Mode::kMip) {
    glBlendEquation(GL_MAX);
    glBlendFunc(GL_ONE, GL_ONE);
  } else if (params.mode == Mode::kAverage) {
    glBlendEquation(GL_FUNC_ADD);
    glBlendFunc(GL_ONE, GL_ONE);
  } else {
    glBlendEquation(GL_FUNC_ADD);
    glBlendFunc(GL_ONE, GL_ONE_MINUS_SRC_ALPHA);
  }

  GLuint p = s.slice_program.id();
  glUseProgram(p);
  auto vp = cam.view_projection().to_float();
  glUniformMatrix4fv(s.loc(p, "u_view_proj"), 1, GL_FALSE, vp.data());
  auto v3 = [&](const char* name, render::Vec3 v) {
    glUniform3f(s.loc(p, name), float(v.x), float(v.y), float(v.z));
  };
  auto f1 = [&](const char* name, double v) { glUniform1f(s.loc(p, name), float(v)); };
  auto i1 = [&](const char* name, int v) { glUniform1i(s.loc(p, name), v); };
  i1("u_mode", int(params.mode));
  v3("u_eye", cam.eye);
  v3("u_forward", cam.forward);
  i1("u_ortho", cam.orthographic ? 1 : 0);
  f1("u_near", cam.near_mm);
  v3("u_origin", g.origin_mm);
  v3("u_spacing", g.spacing_mm);
  v3("u_dims", render::Vec3{double(g.dims[0]), double(g.dims[1]), double(g.dims[2])});
  v3("u_box_lo", box.lo);
  v3("u_box_hi", box.hi);
  f1("u_delta", delta);
  f1("u_delta0", render::reference_length(g));
  f1("u_opacity", params.opacity);
  i1("u_opacity_source", params.opacity_source == render::OpacitySource::kCt ? 1 : 0);
  f1("u_wc", params.window_center_hu);
  f1("u_ww", params.window_width_hu);
  f1("u_iso", params.iso_hu);
  glUniform4f(s.loc(p, "u_iso_colour"), params.iso_colour.r, params.iso_colour.g,
              params.iso_colour.b, params.iso_colour.a);
  i1("u_highlight", params.highlight_label);
  f1("u_dim", params.dim_factor);
  i1("u_jitter", params.jitter ? 1 : 0);
  i1("u_clip", params.clip ? 1 : 0);
  render::Vec3 cn = params.clip_normal;
  glUniform4f(s.loc(p, "u_clip_plane"), float(cn.x), float(cn.y), float(cn.z),
              float(params.clip_d));
  i1("u_has_rgba", volume.has(Channel::kRgba) ? 1 : 0);
  const struct {
    const char* name;
    GLenum target;
    GLuint id;
  } units[] = {{"u_rgba", GL_TEXTURE_3D, volume.texture(Channel::kRgba)},
               {"u_ct", GL_TEXTURE_3D, volume.texture(Channel::kCt)},
               {"u_labels", GL_TEXTURE_3D, volume.texture(Channel::kLabels)},
               {"u_ramp", GL_TEXTURE_2D, s.ramp.id()},
               {"u_label_colours", GL_TEXTURE_2D, s.label_colours.id()}};
  for (int u = 0; u < 5; ++u) {
    glActiveTexture(GL_TEXTURE0 + u);
    glBindTexture(units[u].target, units[u].id);
    i1(units[u].name, u);
  }
  glBindVertexArray(s.vao.id());
  glBindBuffer(GL_ARRAY_BUFFER, s.vbo.id());
  glBufferData(GL_ARRAY_BUFFER, GLsizeiptr(s.vertices.size() * sizeof(float)), s.vertices.data(),
               GL_STREAM_DRAW);
  glDrawArrays(GL_TRIANGLES, 0, GLsizei(tris.size()));
  glBindVertexArray(0);
  glDisable(GL_BLEND);
  glBlendEquation(GL_FUNC_ADD);
  glActiveTexture(GL_TEXTURE0);
  check_gl("rendering slices");
  return info;
}

void SliceRenderer::resolve(GLuint target, int x, int y, int w, int h) {
  Impl& s = *impl_;
  if (!s.acc_texture) throw Error("SliceRenderer::resolve before render");
  glBindFramebuffer(GL_FRAMEBUFFER, target);
  glViewport(x, y, w, h);
  glDisable(GL_BLEND);
  GLuint p = s.resolve_program.id();
  glUseProgram(p);
  glActiveTexture(GL_TEXTURE0);
  glBindTexture(GL_TEXTURE_2D, s.acc_texture.id());
  glUniform1i(s.loc(p, "u_acc"), 0);
  glActiveTexture(GL_TEXTURE1);
  glBindTexture(GL_TEXTURE_2D, s.ramp.id());
  glUniform1i(s.loc(p, "u_ramp"), 1);
  glUniform1i(s.loc(p, "u_mode"), int(s.last.mode));
  glUniform3f(s.loc(p, "u_bg"), s.last.background.r, s.last.background.g, s.last.background.b);
  glUniform1f(s.loc(p, "u_wc"), float(s.last.window_center_hu));
  glUniform1f(s.loc(p, "u_ww"), float(s.last.window_width_hu));
  glUniform2f(s.loc(p, "u_offset"), float(x), float(y));
  glUniform2f(s.loc(p, "u_scale"), float(s.width) / float(std::max(w, 1)),
              float(s.height) / float(std::max(h, 1)));
  glBindVertexArray(s.empty_vao.id());
  glDrawArrays(GL_TRIANGLES, 0, 3);
  glBindVertexArray(0);
  glActiveTexture(GL_TEXTURE0);
  check_gl("resolving the frame");
}

render::Image8 SliceRenderer::read_rgba8() {
  Impl& s = *impl_;
  if (!s.acc_texture) throw Error("SliceRenderer::read_rgba8 before render");
  if (!s.out_texture || s.out_width != s.width || s.out_height != s.height) {
    s.out_texture = make_texture();
    glBindTexture(GL_TEXTURE_2D, s.out_texture.id());
    glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA8, s.width, s.height, 0, GL_RGBA, GL_UNSIGNED_BYTE,
                 nullptr);
    s.out_fbo = make_framebuffer();
    glBindFramebuffer(GL_FRAMEBUFFER, s.out_fbo.id());
    glFramebufferTexture2D(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_TEXTURE_2D, s.out_texture.id(),
                           0);
    s.out_width = s.width;
    s.out_height = s.height;
  }
  resolve(s.out_fbo.id(), 0, 0, s.width, s.height);
  render::Image8 image(s.width, s.height);
  std::vector<std::uint8_t> rows(image.rgba.size());
  glBindFramebuffer(GL_FRAMEBUFFER, s.out_fbo.id());
  glPixelStorei(GL_PACK_ALIGNMENT, 1);
  glReadPixels(0, 0, s.width, s.height, GL_RGBA, GL_UNSIGNED_BYTE, rows.data());
  check_gl("reading the frame");
  std::size_t stride = std::size_t(s.width) * 4;
  for (int y = 0; y < s.height; ++y)
    std::memcpy(&image.rgba[std::size_t(y) * stride], &rows[std::size_t(s.height - 1 - y) * stride],
                stride);
  return image;
}

render::ImageF SliceRenderer::read_accumulation() {
  Impl& s = *impl_;
  if (!s.acc_texture) throw Error("SliceRenderer::read_accumulation before render");
  render::ImageF image(s.width, s.height);
  std::vector<float> rows(image.rgba.size());
  glBindFramebuffer(GL_FRAMEBUFFER, s.acc_fbo.id());
  glPixelStorei(GL_PACK_ALIGNMENT, 4);
  glReadPixels(0, 0, s.width, s.height, GL_RGBA, GL_FLOAT, rows.data());
  check_gl("reading the accumulation buffer");
  std::size_t stride = std::size_t(s.width) * 4;
  for (int y = 0; y < s.height; ++y)
    std::memcpy(&image.rgba[std::size_t(y) * stride], &rows[std::size_t(s.height - 1 - y) * stride],
                stride * sizeof(float));
  return image;
}

}  // namespace vispack::viewer

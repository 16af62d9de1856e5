#include "vispack/viewer/slice_renderer.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>
#include <vector>

#include "shaders.h"
#include "vispack/common/error.h"
#include "vispack/render/reference.h"
#include "vispack/render/slicing.h"

namespace vispack::viewer {

using render::Channel;
using render::Mode;

struct SliceRenderer::Impl {
  // One slice program per mode, compiled at the mode's first frame: u_mode is a compile-time
  // constant, so the driver drops the other modes' code (llvmpipe compiles the shader at the
  // first draw; a smaller shader makes the first picture appear sooner).
  Program slice_programs[8];
  Program resolve_program, terminate_program;
  GLuint slice_program(render::Mode m) {
    const int i = std::clamp(int(m), 0, 7);
    if (!slice_programs[i]) {
      std::string fragment = shaders::kSliceFragment;
      const std::string version = "#version 330 core\n";
      fragment.replace(fragment.find(version), version.size(),
                       version + "#define u_mode " + std::to_string(i) + "\n" +
                           "#define K_MODULATED_FLOOR " + std::to_string(render::kModulatedFloor) +
                           "\n");
      const std::string decl = "uniform int u_mode;\n";
      fragment.erase(fragment.find(decl), decl.size());
      slice_programs[i] =
          make_program(cat("slice (", render::mode_name(m), ")"), shaders::kSliceVertex, fragment);
    }
    return slice_programs[std::size_t(i)].id();
  }
  VertexArray vao, empty_vao;
  Buffer vbo;
  Texture ramp, label_colours, tf2d;
  Texture acc_texture, out_texture, depth_texture;
  Framebuffer acc_fbo, out_fbo, terminate_fbo;
  int width = 0, height = 0, out_width = 0, out_height = 0;
  std::vector<render::Rgba> ramp_data, label_data, tf2d_data;  // last uploaded
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
    // Depth: where early ray termination marks saturated pixels (shared with terminate_fbo).
    depth_texture = make_texture();
    glBindTexture(GL_TEXTURE_2D, depth_texture.id());
    glTexImage2D(GL_TEXTURE_2D, 0, GL_DEPTH_COMPONENT24, w, h, 0, GL_DEPTH_COMPONENT,
                 GL_UNSIGNED_INT, nullptr);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    glBindFramebuffer(GL_FRAMEBUFFER, acc_fbo.id());
    glFramebufferTexture2D(GL_FRAMEBUFFER, GL_DEPTH_ATTACHMENT, GL_TEXTURE_2D, depth_texture.id(),
                           0);
    if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
      throw Error(cat("RGBA32F accumulation framebuffer ", w, "x", h, " is incomplete"));
    terminate_fbo = make_framebuffer();
    glBindFramebuffer(GL_FRAMEBUFFER, terminate_fbo.id());
    glFramebufferTexture2D(GL_FRAMEBUFFER, GL_DEPTH_ATTACHMENT, GL_TEXTURE_2D, depth_texture.id(),
                           0);
    glDrawBuffer(GL_NONE);
    glReadBuffer(GL_NONE);
    if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
      throw Error(cat("termination framebuffer ", w, "x", h, " is incomplete"));
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
    const std::vector<render::Rgba>& t = p.tf2d.table;
    if (t.size() == std::size_t(render::TransferFunction2D::kValues) *
                        render::TransferFunction2D::kGradients &&
        (t.size() != tf2d_data.size() ||
         std::memcmp(t.data(), tf2d_data.data(), t.size() * sizeof(render::Rgba)) != 0)) {
      glBindTexture(GL_TEXTURE_2D, tf2d.id());
      glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA32F, render::TransferFunction2D::kValues,
                   render::TransferFunction2D::kGradients, 0, GL_RGBA, GL_FLOAT, t.data());
      tf2d_data = t;
    }
  }
};

SliceRenderer::SliceRenderer() : impl_(std::make_unique<Impl>()) {
  Impl& s = *impl_;
  s.resolve_program = make_program("resolve", shaders::kResolveVertex, shaders::kResolveFragment);
  s.terminate_program =
      make_program("terminate", shaders::kTerminateVertex, shaders::kTerminateFragment);
  s.vao = make_vertex_array();
  s.empty_vao = make_vertex_array();
  s.vbo = make_buffer();
  glBindVertexArray(s.vao.id());
  glBindBuffer(GL_ARRAY_BUFFER, s.vbo.id());
  glEnableVertexAttribArray(0);
  glVertexAttribPointer(0, 3, GL_FLOAT, GL_FALSE, 3 * sizeof(float), nullptr);
  glBindVertexArray(0);
  for (Texture* t : {&s.ramp, &s.label_colours, &s.tf2d}) {
    *t = make_texture();
    glBindTexture(GL_TEXTURE_2D, t->id());
    bool linear = t != &s.label_colours;
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
  const render::LevelGeometry& g = volume.geometry();
  VolumePiece piece;
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
    piece.texture[int(c)] = volume.texture(c);
  piece.has_rgba = volume.has(Channel::kRgba);
  piece.has_ct = volume.has(Channel::kCt);
  piece.texture_origin_mm = g.origin_mm;
  piece.spacing_mm = g.spacing_mm;
  piece.texture_dims = g.dims;
  piece.box = g.box();
  piece.slice_spacing_mm = render::slice_spacing(cam, g, params.slices_per_voxel);
  double delta0 =
      params.reference_length_mm > 0 ? params.reference_length_mm : render::reference_length(g);
  return render_pieces({piece}, cam, params, piece.box, delta0);
}

FrameInfo SliceRenderer::render_bricks(const BrickCache& cache, const render::BrickTree& tree,
                                       const render::BrickPlan& plan, const render::Camera& cam,
                                       const render::RenderParams& params) {
  std::vector<VolumePiece> pieces;
  pieces.reserve(plan.draw.size());
  const unsigned present = tree.present_channels();
  const bool skip_cells =
      params.mode != Mode::kMip && params.mode != Mode::kAverage && params.mode != Mode::kMpr;
  const unsigned needed = render::channels_for(params, present);
  render::Vec3 eye_point = cam.eye;
  if (cam.orthographic)
    eye_point = cam.eye - cam.forward * (1e6 * render::length(tree.volume_box().size()) + 1e6);
  std::int64_t cells_skipped = 0;
  std::vector<std::int64_t> order;
  for (const render::BrickKey& key : plan.draw) {
    const BrickCache::Brick* b = cache.find(key);
    if (!b) continue;
    const render::LevelGeometry& g = tree.level(key.level);
    VolumePiece p;
    for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
      p.texture[int(c)] = b->texture[int(c)] ? b->texture[int(c)] : cache.zero_texture(c);
    p.has_rgba = present & render::channel_bit(Channel::kRgba);
    p.has_ct = present & render::channel_bit(Channel::kCt);
    p.texture_origin_mm =
        g.origin_mm +
        render::mul(render::Vec3{double(b->offset[0]), double(b->offset[1]), double(b->offset[2])},
                    g.spacing_mm);
    p.spacing_mm = g.spacing_mm;
    p.texture_dims = b->dims;
    p.box = tree.brick_box(key);
    p.slice_spacing_mm = render::slice_spacing(cam, g, params.slices_per_voxel);
    const render::CellGrid& cells = b->cells;
    if (!skip_cells || cells.ranges.empty() || (cells.channels & needed) != needed) {
      pieces.push_back(p);
      continue;
    }
    // Cells of the brick, back to front (grid rule), each drawn only if it may contribute.
    const render::Box3 brick_box = p.box;
    render::Vec3 lo, size;
    double eye_cell[3];
    for (int a = 0; a < 3; ++a) {
      lo[a] = g.origin_mm[a] + (double(key.brick[a] * tree.brick_edge()) - 0.5) * g.spacing_mm[a];
      size[a] = cells.cell * g.spacing_mm[a];
      eye_cell[a] = std::floor((eye_point[a] - lo[a]) / size[a]);
    }
    order.resize(cells.ranges.size());
    for (std::size_t i = 0; i < order.size(); ++i)
      order[i] = std::int64_t(i);
    auto coord = [&](std::int64_t i, int a) {
      std::int64_t x = i % cells.dims[0], y = (i / cells.dims[0]) % cells.dims[1],
                   z = i / (cells.dims[0] * cells.dims[1]);
      return a == 0 ? x : (a == 1 ? y : z);
    };
    std::stable_sort(order.begin(), order.end(), [&](std::int64_t u, std::int64_t v) {
      for (int a = 2; a >= 0; --a) {
        double ku = std::fabs(double(coord(u, a)) - eye_cell[a]);
        double kv = std::fabs(double(coord(v, a)) - eye_cell[a]);
        if (ku != kv) return ku > kv;
      }
      return false;
    });
    for (std::int64_t i : order) {
      if (!render::range_may_contribute(cells.ranges[std::size_t(i)], params)) {
        ++cells_skipped;
        continue;
      }
      VolumePiece c = p;
      for (int a = 0; a < 3; ++a) {
        c.box.lo[a] = std::max(brick_box.lo[a], lo[a] + double(coord(i, a)) * size[a]);
        c.box.hi[a] = std::min(brick_box.hi[a], lo[a] + double(coord(i, a) + 1) * size[a]);
      }
      if (c.box.valid() && c.box.lo.x < c.box.hi.x && c.box.lo.y < c.box.hi.y &&
          c.box.lo.z < c.box.hi.z)
        pieces.push_back(c);
    }
  }
  double delta0 = params.reference_length_mm > 0 ? params.reference_length_mm
                                                 : render::reference_length(tree.level(0));
  FrameInfo info = render_pieces(pieces, cam, params, tree.volume_box(), delta0);
  info.cells_skipped = cells_skipped;
  return info;
}

FrameInfo SliceRenderer::render_pieces(const std::vector<VolumePiece>& pieces,
                                       const render::Camera& cam,
                                       const render::RenderParams& params,
                                       const render::Box3& volume_box, double delta0) {
  Impl& s = *impl_;
  FrameInfo info;
  s.ensure_targets(std::max(cam.width, 1), std::max(cam.height, 1));
  s.upload_tables(params);
  s.last = params;

  // Order: front to back with early ray termination for the compositing modes (associated
  // colour "under" blending; isosurface: the nearest hit saturates the pixel); back to front
  // for mip and average, whose blending does not depend on the order.
  const bool front_to_back = params.mode != Mode::kMip && params.mode != Mode::kAverage;
  // Proxy geometry per piece on the world-fixed lattice, or the MPR plane; slice_ends[i] holds
  // the vertex index after each slice of piece i (the draw is split between slices).
  const double near_d = render::dot(cam.forward, cam.eye) + cam.near_mm;
  std::vector<std::vector<std::size_t>> slice_ends(pieces.size());
  std::vector<std::size_t> piece_first(pieces.size());
  std::vector<render::Vec3> tris;
  info.slice_spacing_mm = 0;
  const double volume_dmin = render::box_dmin(volume_box, cam.forward);
  auto add_polygon = [&](const std::vector<render::Vec3>& poly) {
    for (std::size_t j = 1; j + 1 < poly.size(); ++j)
      tris.insert(tris.end(), {poly[0], poly[j], poly[j + 1]});
  };
  for (std::size_t i = 0; i < pieces.size(); ++i) {
    const VolumePiece& piece = pieces[i];
    piece_first[i] = tris.size();
    if (params.mode == Mode::kMpr) {
      double d = render::dot(cam.forward, params.mpr_target + cam.forward * params.mpr_offset_mm);
      if (d > near_d) {
        std::vector<render::Vec3> poly = render::slice_polygon(piece.box, cam.forward, d);
        add_polygon(poly);
        info.slices += poly.empty() ? 0 : 1;
      }
      slice_ends[i].push_back(tris.size());
    } else {
      render::SliceLattice lat = render::slice_lattice_tile(
          piece.box, cam.forward, piece.slice_spacing_mm, near_d, volume_dmin);
      for (std::int64_t k = 0; k < lat.count; ++k) {
        std::int64_t idx = front_to_back ? k : lat.count - 1 - k;
        add_polygon(render::slice_polygon(piece.box, lat.normal, lat.d(idx)));
        slice_ends[i].push_back(tris.size());
      }
      info.slices += lat.count;
    }
    if (info.slice_spacing_mm == 0 || piece.slice_spacing_mm < info.slice_spacing_mm)
      info.slice_spacing_mm = piece.slice_spacing_mm;
  }
  info.pieces = std::int64_t(pieces.size());
  info.triangles = std::int64_t(tris.size() / 3);
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
  glDepthMask(GL_TRUE);
  glClearDepth(1.0);
  glClear(GL_COLOR_BUFFER_BIT | GL_DEPTH_BUFFER_BIT);
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
    glBlendFunc(GL_ONE_MINUS_DST_ALPHA, GL_ONE);  // front to back: acc += (1 − acc.a)·src
  }
  if (front_to_back) {
    glEnable(GL_DEPTH_TEST);
    glDepthFunc(GL_LESS);
    glDepthMask(GL_FALSE);
  }

  GLuint p = s.slice_program(params.mode);
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
  v3("u_box_lo", volume_box.lo);
  v3("u_box_hi", volume_box.hi);
  f1("u_delta0", delta0);
  f1("u_opacity", params.opacity);
  i1("u_opacity_source", params.opacity_source == render::OpacitySource::kCt ? 1 : 0);
  f1("u_wc", params.window_center_hu);
  f1("u_ww", params.window_width_hu);
  f1("u_iso", params.iso_hu);
  i1("u_iso_steps", render::kIsoBisectionSteps);
  glUniform4f(s.loc(p, "u_iso_colour"), params.iso_colour.r, params.iso_colour.g,
              params.iso_colour.b, params.iso_colour.a);
  i1("u_highlight", params.highlight_label);
  f1("u_dim", params.dim_factor);
  i1("u_label_shading", int(params.label_shading));
  v3("u_tf_range", {params.tf2d.value_min, params.tf2d.value_max, params.tf2d.gradient_max});
  i1("u_jitter", params.jitter ? 1 : 0);
  i1("u_clip", params.clip ? 1 : 0);
  render::Vec3 cn = params.clip_normal;
  glUniform4f(s.loc(p, "u_clip_plane"), float(cn.x), float(cn.y), float(cn.z),
              float(params.clip_d));
  const char* samplers[] = {"u_rgba", "u_ct", "u_labels", "u_ramp", "u_label_colours", "u_tf2d"};
  for (int u = 0; u < 6; ++u)
    i1(samplers[u], u);
  glActiveTexture(GL_TEXTURE3);
  glBindTexture(GL_TEXTURE_2D, s.ramp.id());
  glActiveTexture(GL_TEXTURE4);
  glBindTexture(GL_TEXTURE_2D, s.label_colours.id());
  glActiveTexture(GL_TEXTURE5);
  glBindTexture(GL_TEXTURE_2D, s.tf2d.id());
  glBindVertexArray(s.vao.id());
  glBindBuffer(GL_ARRAY_BUFFER, s.vbo.id());
  glBufferData(GL_ARRAY_BUFFER, GLsizeiptr(s.vertices.size() * sizeof(float)), s.vertices.data(),
               GL_STREAM_DRAW);
  // Early ray termination: about 24 times a frame (and at least every 64 slices drawn), a
  // full-screen pass writes depth 0 where the accumulated opacity reached kSaturated (what is
  // left can change a pixel by less than a quarter of an 8-bit level).
  constexpr std::size_t kBatch = 16;
  constexpr float kSaturated = 0.999f;
  std::size_t total_slices = 0;
  for (const auto& ends : slice_ends)
    total_slices += ends.size();
  const std::size_t pass_every = std::max<std::size_t>(64, total_slices / 24);
  std::size_t since_pass = 0;
  const VolumePiece* bound = nullptr;
  auto terminate = [&]() {
    glBindFramebuffer(GL_FRAMEBUFFER, s.terminate_fbo.id());
    glDisable(GL_BLEND);
    glDepthFunc(GL_ALWAYS);
    glDepthMask(GL_TRUE);
    GLuint t = s.terminate_program.id();
    glUseProgram(t);
    glActiveTexture(GL_TEXTURE6);
    glBindTexture(GL_TEXTURE_2D, s.acc_texture.id());
    glUniform1i(s.loc(t, "u_acc"), 6);
    glUniform1f(s.loc(t, "u_threshold"), kSaturated);
    glBindVertexArray(s.empty_vao.id());
    glDrawArrays(GL_TRIANGLES, 0, 3);
    glBindFramebuffer(GL_FRAMEBUFFER, s.acc_fbo.id());
    glEnable(GL_BLEND);
    glDepthFunc(GL_LESS);
    glDepthMask(GL_FALSE);
    glUseProgram(p);
    glBindVertexArray(s.vao.id());
  };
  for (std::size_t n = 0; n < pieces.size(); ++n) {
    const std::size_t i = front_to_back ? pieces.size() - 1 - n : n;
    const std::vector<std::size_t>& ends = slice_ends[i];
    if (ends.empty() || ends.back() == piece_first[i]) continue;
    const VolumePiece& piece = pieces[i];
    if (!bound || std::memcmp(bound->texture, piece.texture, sizeof(piece.texture)) != 0) {
      for (int c = 0; c < render::kChannelCount; ++c) {
        glActiveTexture(GLenum(GL_TEXTURE0 + c));
        glBindTexture(GL_TEXTURE_3D, piece.texture[c]);
      }
    }
    bound = &piece;
    v3("u_origin", piece.texture_origin_mm);
    v3("u_spacing", piece.spacing_mm);
    v3("u_dims", render::Vec3{double(piece.texture_dims[0]), double(piece.texture_dims[1]),
                              double(piece.texture_dims[2])});
    f1("u_delta", piece.slice_spacing_mm);
    i1("u_has_rgba", piece.has_rgba ? 1 : 0);
    i1("u_has_ct", piece.has_ct ? 1 : 0);
    std::size_t first = piece_first[i];
    for (std::size_t k = 0; k < ends.size(); k += kBatch) {
      const std::size_t end = ends[std::min(k + kBatch, ends.size()) - 1];
      if (end > first) {
        if (front_to_back && since_pass >= pass_every) {
          terminate();
          since_pass = 0;
        }
        glDrawArrays(GL_TRIANGLES, GLint(first), GLsizei(end - first));
      }
      since_pass += std::min(kBatch, ends.size() - k);
      first = end;
    }
  }
  glDisable(GL_DEPTH_TEST);
  glDepthMask(GL_TRUE);
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

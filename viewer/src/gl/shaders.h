// GLSL sources of the slice renderer (private to vispack_viewer_gl). They implement the
// formulas of render/transfer.h and render/reference.h; keep the two in step.
#pragma once

namespace vispack::viewer::shaders {

inline constexpr const char* kSliceVertex = R"(#version 330 core
layout(location = 0) in vec3 a_world;
uniform mat4 u_view_proj;
out vec3 v_world;
void main() {
  v_world = a_world;
  gl_Position = u_view_proj * vec4(a_world, 1.0);
}
)";

// Mode numbers follow render::Mode: 0 colour, 1 ct, 2 mip, 3 average, 4 iso, 5 labels, 6 mpr,
// 7 tf2d. Label shading follows render::LabelShading: 0 flat, 1 modulated, 2 ramp. The program
// builder defines u_mode and K_MODULATED_FLOOR (render::kModulatedFloor) before compiling.
inline constexpr const char* kSliceFragment = R"(#version 330 core
in vec3 v_world;
layout(location = 0) out vec4 o_colour;
uniform int u_mode;
uniform vec3 u_eye;
uniform vec3 u_forward;
uniform int u_ortho;
uniform float u_near;
uniform vec3 u_origin;
uniform vec3 u_spacing;
uniform vec3 u_dims;
uniform vec3 u_box_lo;
uniform vec3 u_box_hi;
uniform float u_delta;
uniform float u_delta0;
uniform float u_opacity;
uniform int u_opacity_source;
uniform float u_wc;
uniform float u_ww;
uniform float u_iso;
uniform vec4 u_iso_colour;
uniform int u_highlight;
uniform float u_dim;
uniform int u_jitter;
uniform int u_clip;
uniform vec4 u_clip_plane;
uniform int u_has_rgba;
uniform int u_has_ct;
uniform int u_label_shading;
uniform int u_iso_steps;
uniform vec3 u_tf_range;  // value min, value max (HU), gradient max (HU/mm)
uniform sampler2D u_tf2d;
uniform sampler3D u_rgba;
uniform sampler3D u_ct;
uniform usampler3D u_labels;
uniform sampler2D u_ramp;
uniform sampler2D u_label_colours;

vec3 voxel(vec3 p) { return (p - u_origin) / u_spacing; }
vec3 tex(vec3 p) { return (voxel(p) + 0.5) / u_dims; }
float hu_at(vec3 p) { return texture(u_ct, tex(p)).r * 32767.0; }
vec4 colour_at(vec3 p) { return texture(u_rgba, tex(p)); }
uint label_at(vec3 p) {
  vec3 v = clamp(floor(voxel(p) + 0.5), vec3(0.0), u_dims - 1.0);
  return texelFetch(u_labels, ivec3(v), 0).r;
}
float window01(float hu) {
  if (!(u_ww > 0.0)) return hu >= u_wc ? 1.0 : 0.0;
  return clamp((hu - (u_wc - 0.5 * u_ww)) / u_ww, 0.0, 1.0);
}
vec4 ramp(float t) { return texture(u_ramp, vec2((clamp(t, 0.0, 1.0) * 255.0 + 0.5) / 256.0, 0.5)); }
float correct(float a, float ratio) {
  if (!(a > 0.0)) return 0.0;
  if (a >= 1.0) return 1.0;
  return 1.0 - pow(1.0 - a, ratio);
}
vec3 gradient_at(vec3 p) {
  return vec3(hu_at(p + vec3(u_spacing.x, 0.0, 0.0)) - hu_at(p - vec3(u_spacing.x, 0.0, 0.0)),
              hu_at(p + vec3(0.0, u_spacing.y, 0.0)) - hu_at(p - vec3(0.0, u_spacing.y, 0.0)),
              hu_at(p + vec3(0.0, 0.0, u_spacing.z)) - hu_at(p - vec3(0.0, 0.0, u_spacing.z))) /
         (2.0 * u_spacing);
}
vec4 tf2d(float v, float g) {
  float t = clamp((v - u_tf_range.x) / max(u_tf_range.y - u_tf_range.x, 1e-6), 0.0, 1.0);
  float u = clamp(g / max(u_tf_range.z, 1e-6), 0.0, 1.0);
  return texture(u_tf2d, vec2((t * 127.0 + 0.5) / 128.0, (u * 63.0 + 0.5) / 64.0));
}
float label_intensity(vec3 p) {
  if (u_has_ct != 0) return window01(hu_at(p));
  vec4 c = colour_at(p);
  vec3 rgb = min(c.rgb / max(c.a, 1e-6), vec3(1.0));
  return dot(rgb, vec3(0.299, 0.587, 0.114));
}
vec3 shade_label(vec3 c, float t) {
  t = clamp(t, 0.0, 1.0);
  if (u_label_shading == 1) return c * (K_MODULATED_FLOOR + (1.0 - K_MODULATED_FLOOR) * t);
  if (t < 0.5) return c * (2.0 * t);
  return c + (vec3(1.0) - c) * (2.0 * t - 1.0);
}
float hash(vec2 q) { return fract(sin(dot(q, vec2(12.9898, 78.233))) * 43758.5453); }

vec4 classify(vec3 p) {
  if (u_mode == 0) {
    vec4 c = colour_at(p);
    vec3 rgb = min(c.rgb / max(c.a, 1e-6), vec3(1.0));
    float a = u_opacity_source == 1 ? window01(hu_at(p)) : c.a;
    return vec4(rgb, u_opacity * a);
  }
  if (u_mode == 1) {
    float t = window01(hu_at(p));
    vec4 c = ramp(t);
    return vec4(c.rgb, u_opacity * t * c.a);
  }
  if (u_mode == 7) {
    vec4 c = tf2d(hu_at(p), length(gradient_at(p)));
    return vec4(c.rgb, u_opacity * c.a);
  }
  uint id = label_at(p);
  if (id == 0u) return vec4(0.0);
  vec4 c = texelFetch(u_label_colours, ivec2(int(id & 255u), int(id >> 8u)), 0);
  float f = (u_highlight >= 0 && int(id) != u_highlight) ? u_dim : 1.0;
  vec3 rgb = u_label_shading != 0 ? shade_label(c.rgb, label_intensity(p)) : c.rgb;
  return vec4(rgb, c.a * u_opacity * f);
}

vec4 shade(vec4 colour, vec3 g, vec3 dir) {
  vec3 view = -dir;
  vec3 n = view;
  float len = length(g);
  if (len > 1e-6) n = -g / len;
  float ndl = dot(n, view);
  float diffuse = abs(ndl);
  vec3 r = n * (2.0 * ndl) - view;
  float spec = pow(max(dot(r, view), 0.0), 32.0);
  return vec4(clamp(colour.rgb * (0.25 + 0.65 * diffuse) + 0.25 * spec, 0.0, 1.0), 1.0);
}

void main() {
  vec3 dir = u_ortho != 0 ? u_forward : normalize(v_world - u_eye);
  float cosf = max(dot(dir, u_forward), 1e-6);
  float dray = u_delta / cosf;
  vec3 p = v_world;
  if (u_jitter != 0) p += dir * (dray * (hash(gl_FragCoord.xy) - 0.5));
  // No discard anywhere (it would disable llvmpipe's early depth test, which the early ray
  // termination relies on): a removed sample writes the blend's neutral value instead.
  // The sample stands for the ray segment [−dray/2, +dray/2] around p. The compositing modes
  // keep the part of it inside the volume box and on the kept side of the clip plane: its
  // length, and where a face or the plane cuts into the segment from the eye's side, the sample
  // moves onto it (a cut face or the box's face is sampled where it is, not up to a slice
  // spacing behind it: no staircase there). The other modes remove the sample when p is clipped.
  const bool compositing = u_mode == 0 || u_mode == 1 || u_mode == 5 || u_mode == 7;
  float side = u_clip != 0 ? dot(u_clip_plane.xyz, p) - u_clip_plane.w : -1.0;  // > 0: removed
  if (compositing) {
    float lo = -0.5 * dray, hi = 0.5 * dray;
    vec3 d = dir;
    for (int a = 0; a < 3; ++a)
      if (abs(d[a]) < 1e-12) d[a] = 1e-12;
    vec3 ta = (u_box_lo - p) / d, tb = (u_box_hi - p) / d;
    vec3 tmin = min(ta, tb), tmax = max(ta, tb);
    lo = max(lo, max(max(tmin.x, tmin.y), tmin.z));
    hi = min(hi, min(min(tmax.x, tmax.y), tmax.z));
    if (u_clip != 0) {
      float nd = dot(u_clip_plane.xyz, dir);
      if (abs(nd) > 1e-7) {
        float u0 = -side / nd;
        if (nd > 0.0) hi = min(hi, u0); else lo = max(lo, u0);
      } else if (side > 0.0) {
        hi = lo;
      }
    }
    if (hi <= lo) {
      o_colour = vec4(0.0);
      return;
    }
    p += dir * (lo > -0.5 * dray ? lo : min(0.0, hi));
    dray = hi - lo;
  } else if (side > 0.0) {
    o_colour = u_mode == 2 ? vec4(-1e30, 0.0, 0.0, 0.0) : vec4(0.0);
    return;
  }
  if (u_mode == 2) {
    o_colour = vec4(hu_at(p), 1.0, 0.0, 0.0);
    return;
  }
  if (u_mode == 3) {
    o_colour = vec4(hu_at(p) * dray, dray, 0.0, 0.0);
    return;
  }
  if (u_mode == 6) {
    o_colour = u_has_rgba != 0 ? colour_at(p) : vec4(ramp(window01(hu_at(p))).rgb, 1.0);
    return;
  }
  if (u_mode == 4) {
    float f = hu_at(p);
    if (f < u_iso) {
      o_colour = vec4(0.0);
      return;
    }
    vec3 ro = u_ortho != 0 ? p - dir * dot(p - u_eye, u_forward) : u_eye;
    float tp = dot(p - ro, dir);
    vec3 d = dir;
    for (int a = 0; a < 3; ++a)
      if (abs(d[a]) < 1e-12) d[a] = 1e-12;
    vec3 ta = (u_box_lo - ro) / d;
    vec3 tb = (u_box_hi - ro) / d;
    vec3 tmin = min(ta, tb);
    float t0 = max(max(tmin.x, tmin.y), tmin.z);
    t0 = max(t0, u_ortho != 0 ? u_near : u_near / cosf);
    float tprev = max(tp - dray, t0);
    float fprev = hu_at(ro + dir * tprev);
    float th = tp;
    if (fprev >= u_iso) {
      th = tprev;
    } else {
      // Bisection between the two samples that bracket the crossing (render::refine_iso).
      float ta = tprev, fa = fprev, tb = tp, fb = f;
      for (int i = 0; i < u_iso_steps; ++i) {
        float tm = 0.5 * (ta + tb);
        float fm = hu_at(ro + dir * tm);
        if (fm >= u_iso) { tb = tm; fb = fm; } else { ta = tm; fa = fm; }
      }
      th = fb > fa ? ta + (tb - ta) * (u_iso - fa) / (fb - fa) : tb;
    }
    vec3 hit = ro + dir * th;
    o_colour = shade(u_iso_colour, gradient_at(hit), dir);
    return;
  }
  vec4 s = classify(p);
  float a = correct(s.a, dray / u_delta0);
  o_colour = vec4(s.rgb * a, a);
}
)";

// Early ray termination (front-to-back modes): a full-screen triangle at the near plane
// (depth 0) that writes depth only where the accumulated opacity is saturated, so the depth
// test (GL_LESS) rejects every later slice fragment there before it is shaded.
inline constexpr const char* kTerminateVertex = R"(#version 330 core
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, -1.0, 1.0);
}
)";
inline constexpr const char* kTerminateFragment = R"(#version 330 core
uniform sampler2D u_acc;
uniform float u_threshold;
void main() {
  if (texelFetch(u_acc, ivec2(gl_FragCoord.xy), 0).a < u_threshold) discard;
}
)";

inline constexpr const char* kResolveVertex = R"(#version 330 core
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
)";

inline constexpr const char* kResolveFragment = R"(#version 330 core
layout(location = 0) out vec4 o_colour;
uniform sampler2D u_acc;
uniform sampler2D u_ramp;
uniform int u_mode;
uniform vec3 u_bg;
uniform float u_wc;
uniform float u_ww;
uniform vec2 u_offset;
uniform vec2 u_scale;
float window01(float hu) {
  if (!(u_ww > 0.0)) return hu >= u_wc ? 1.0 : 0.0;
  return clamp((hu - (u_wc - 0.5 * u_ww)) / u_ww, 0.0, 1.0);
}
vec4 ramp(float t) { return texture(u_ramp, vec2((clamp(t, 0.0, 1.0) * 255.0 + 0.5) / 256.0, 0.5)); }
void main() {
  ivec2 size = textureSize(u_acc, 0);
  ivec2 src = clamp(ivec2((gl_FragCoord.xy - u_offset) * u_scale), ivec2(0), size - 1);
  vec4 a = texelFetch(u_acc, src, 0);
  if (u_mode == 2 || u_mode == 3) {
    if (a.g > 0.0) {
      float v = u_mode == 2 ? a.r : a.r / a.g;
      o_colour = vec4(ramp(window01(v)).rgb, 1.0);
    } else {
      o_colour = vec4(u_bg, 0.0);
    }
    return;
  }
  o_colour = vec4(a.rgb + (1.0 - a.a) * u_bg, a.a);
}
)";

}  // namespace vispack::viewer::shaders

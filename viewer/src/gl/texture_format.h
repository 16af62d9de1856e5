// GL texture formats of the volume channels (private to vispack_viewer_gl), shared by the
// whole-level textures (volume_textures.cpp) and the brick cache (brick_cache.cpp).
#pragma once

#include <epoxy/gl.h>

#include <array>
#include <cstdint>

#include "vispack/render/volume.h"
#include "vispack/viewer/gl_objects.h"

namespace vispack::viewer::detail {

struct TextureFormat {
  GLint internal;
  GLenum format, type;
  GLint filter;
};

inline TextureFormat format_of(render::Channel c) {
  switch (c) {
    case render::Channel::kRgba:
      return {GL_RGBA8, GL_RGBA, GL_UNSIGNED_BYTE, GL_LINEAR};
    case render::Channel::kCt:
      return {GL_R16_SNORM, GL_RED, GL_SHORT, GL_LINEAR};
    case render::Channel::kLabels:
      return {GL_R16UI, GL_RED_INTEGER, GL_UNSIGNED_SHORT, GL_NEAREST};
  }
  return {GL_RGBA8, GL_RGBA, GL_UNSIGNED_BYTE, GL_LINEAR};
}

// A 3-D texture of channel `c` with `dims` texels, clamped to edge, one mip level; filled from
// `data` when it is not null. Leaves it bound to GL_TEXTURE_3D.
inline Texture allocate_texture(render::Channel c, const std::array<std::int64_t, 3>& dims,
                                const void* data = nullptr) {
  TextureFormat f = format_of(c);
  Texture t = make_texture();
  glBindTexture(GL_TEXTURE_3D, t.id());
  glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MIN_FILTER, f.filter);
  glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MAG_FILTER, f.filter);
  for (GLenum w : {GL_TEXTURE_WRAP_S, GL_TEXTURE_WRAP_T, GL_TEXTURE_WRAP_R})
    glTexParameteri(GL_TEXTURE_3D, w, GL_CLAMP_TO_EDGE);
  glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MAX_LEVEL, 0);
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  glTexImage3D(GL_TEXTURE_3D, 0, f.internal, GLsizei(dims[0]), GLsizei(dims[1]), GLsizei(dims[2]),
               0, f.format, f.type, data);
  check_gl("allocating a 3-D texture");
  return t;
}

}  // namespace vispack::viewer::detail

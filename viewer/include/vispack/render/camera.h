// Camera math shared by the GL renderer and the CPU reference ray caster (no GL dependency).
//
// World frame: millimetres in the volume's frame (docs/ARCHITECTURE.md): x = image column,
// y = image row (downwards), z = slice index. The orbit camera keeps "up" on screen along −z
// (slice 0, the head of a Visible Human stack, at the top).
//
// Orbit convention: azimuth 0, elevation 0 looks along −y (from the +y side), with +x to the
// right of the screen. Positive azimuth turns the camera about the z axis; positive elevation
// raises the camera towards −z (looking down on the head).
//
// Pixel convention: an image of width W and height H; pixel (i, j) has column i from the left
// and row j from the top, and its centre at (i + 0.5, j + 0.5). Both renderers shoot (or
// rasterise) exactly one sample at each pixel centre.
#pragma once

#include "vispack/render/math.h"

namespace vispack::render {

struct Box3;

struct Ray {
  Vec3 origin;     // world mm
  Vec3 direction;  // unit vector
};

// A posed camera with its projection. All vectors are in world mm; forward/right/up are an
// orthonormal, right-handed basis (right = forward × up_hint normalised, up = right × forward).
struct Camera {
  Vec3 eye{0, 0, 0};
  Vec3 forward{0, 0, 1};
  Vec3 right{1, 0, 0};
  Vec3 up{0, -1, 0};
  bool orthographic = false;
  double fov_y_deg = 30.0;         // perspective: full vertical field of view
  double ortho_half_height = 1.0;  // orthographic: half the visible height, in mm
  double near_mm = 0.01;           // distance of the near plane along `forward` (> 0)
  double far_mm = 1e4;             // distance of the far plane along `forward` (> near)
  int width = 1;                   // image size in pixels (> 0)
  int height = 1;

  // Ray through continuous pixel coordinates (px, py) (pixel centres at +0.5, see above).
  // Perspective rays start at the eye, orthographic rays on the plane through the eye.
  Ray ray(double px, double py) const;
  // World → eye (OpenGL convention: the camera looks down −z in eye space).
  Mat4 view_matrix() const;
  // Eye → clip space (OpenGL convention: NDC depth in [−1, 1]).
  Mat4 projection_matrix() const;
  Mat4 view_projection() const { return projection_matrix() * view_matrix(); }
};

// Parameters of an orbit camera about `target`. distance <= 0 means "fit the box".
struct OrbitParams {
  Vec3 target{0, 0, 0};
  double azimuth_deg = 0.0;
  double elevation_deg = 0.0;
  double distance_mm = 0.0;  // <= 0: fit_distance(box) / zoom
  double zoom = 1.0;         // > 0; divides the fitted distance (or the ortho half height)
  double fov_y_deg = 30.0;
  bool orthographic = false;
  Vec3 pan_mm{0, 0, 0};  // added to both eye and target (a translation of the camera)
};

// Distance from the box centre at which a perspective camera of `fov_y_deg` sees the whole
// bounding sphere of `box` (or 1 for an empty/invalid box).
double fit_distance(const Box3& box, double fov_y_deg);

// Builds a camera for an orbit around params.target looking at it. Near and far planes are
// chosen to enclose `box`; with the eye inside the box, near is 1e-3 of the box diagonal.
// Non-finite inputs are replaced by defaults (never NaN in the result). Elevation is clamped
// to ±89.9° so the up vector stays defined.
Camera orbit_camera(const OrbitParams& params, const Box3& box, int width, int height);

}  // namespace vispack::render

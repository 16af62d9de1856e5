// Compositing, opacity correction, sampling and the CPU reference ray caster.
#include <gtest/gtest.h>

#include <cmath>
#include <stdexcept>

#include "synthetic_volume.h"
#include "vispack/render/reference.h"

using namespace vispack::render;

TEST(Opacity, CorrectionEdgeCases) {
  EXPECT_EQ(opacity_correct(0.0, 0.5), 0.0);
  EXPECT_EQ(opacity_correct(1.0, 0.5), 1.0);
  EXPECT_EQ(opacity_correct(1.0 + 1e-7, 0.5), 1.0);  // no pow of a negative base
  EXPECT_EQ(opacity_correct(1.5, 3.0), 1.0);
  EXPECT_EQ(opacity_correct(-0.2, 2.0), 0.0);
  EXPECT_EQ(opacity_correct(std::nan(""), 2.0), 0.0);
  EXPECT_FALSE(std::isnan(opacity_correct(0.3, std::nan(""))));
  EXPECT_NEAR(opacity_correct(0.3, 1.0), 0.3, 1e-15);
  EXPECT_NEAR(opacity_correct(0.3, 2.0), 1 - 0.7 * 0.7, 1e-15);
  // Two half steps compose to one full step (the property that makes slice density free).
  double half = opacity_correct(0.3, 0.5);
  EXPECT_NEAR(1 - (1 - half) * (1 - half), 0.3, 1e-15);
}

TEST(Compositing, EqualSlicesMatchTheClosedForm) {
  // docs/GOALS.md §4: at alpha = 0.002 an 8-bit buffer loses everything after ~1000 slices; float
  // accumulation must follow 1 - (1 - a)^N. Tolerance 1e-4: float rounding over 4000 steps.
  for (double a : {0.002, 0.05, 0.5}) {
    for (int n : {1, 10, 1000, 4000}) {
      Rgba over, under;
      const Rgba s{float(0.8 * a), float(0.4 * a), float(0.2 * a), float(a)};
      for (int i = 0; i < n; ++i) {
        composite_over(over, s);
        composite_under(under, s);
      }
      double expect = 1 - std::pow(1 - a, n);
      EXPECT_NEAR(over.a, expect, 1e-4) << a << " " << n;
      EXPECT_NEAR(under.a, expect, 1e-4) << a << " " << n;
      EXPECT_NEAR(over.r, 0.8 * expect, 1e-4);
      EXPECT_NEAR(under.b, 0.2 * expect, 1e-4);
    }
  }
  // The same with 8-bit rounding after each step (what an RGBA8 target does) fails badly.
  double acc8 = 0;
  for (int i = 0; i < 1000; ++i)
    acc8 = std::round((0.002 + (1 - 0.002) * acc8) * 255) / 255;
  EXPECT_GT(std::fabs(acc8 - (1 - std::pow(0.998, 1000))), 0.5);
}

namespace {
// A 2x1x1 volume: opaque red voxel beside a transparent blue (gel) voxel.
VolumeData edge_volume() {
  VolumeData v;
  v.geometry.dims = {2, 1, 1};
  v.rgba = {255, 0, 0, 255, 0, 0, 255, 0};
  return v;
}
}  // namespace

TEST(Compositing, NoHaloAtAnOpaqueTransparentEdge) {
  VolumeData v = edge_volume();
  VolumeSampler sampler(v);
  RenderParams params;
  for (double x : {0.1, 0.5, 0.9}) {
    Rgba c = classify(sampler, params, {x, 0, 0});
    EXPECT_NEAR(c.r, 1.0, 1e-6) << x;
    EXPECT_EQ(c.b, 0.0f) << x;  // premultiplied interpolation: the gel colour adds nothing
    EXPECT_NEAR(c.a, 1.0 - x, 1e-6);
  }
  // Straight (non-premultiplied) interpolation would tint the edge blue: the halo this avoids.
  double straight_blue = 0.5 * 0 + 0.5 * 1.0;
  EXPECT_GT(straight_blue, 0.4);
}

TEST(Compositing, Labels1And3NeverBecome2) {
  VolumeData v;
  v.geometry.dims = {2, 1, 2};
  v.labels = {1, 3, 3, 1};
  VolumeSampler sampler(v);
  for (int i = 0; i <= 1000; ++i) {
    double x = -0.5 + 2.0 * i / 1000.0;
    for (double z : {-0.3, 0.2, 0.5, 0.8, 1.4}) {
      std::uint16_t id = sampler.label({x, 0, z});
      EXPECT_TRUE(id == 1 || id == 3) << x << " " << z << " -> " << id;
    }
  }
  // Linear interpolation of the IDs (what a filtered texture would do) gives 2 half way.
  EXPECT_EQ(std::lround(0.5 * 1 + 0.5 * 3), 2);
}

TEST(Shading, ZeroGradientIsSafe) {
  Rgba c{0.5f, 0.6f, 0.7f, 1.0f};
  Rgba zero = shade_iso(c, {0, 0, 0}, {0, 0, 1});
  Rgba facing = shade_iso(c, {0, 0, 1}, {0, 0, 1});  // normal -g = -z faces the viewer
  for (Rgba s : {zero, facing, shade_iso(c, {NAN, 0, 0}, {0, 0, 1}),
                 shade_iso(c, {1e-30, 0, 0}, {0, 0, 1})}) {
    EXPECT_TRUE(std::isfinite(s.r) && std::isfinite(s.g) && std::isfinite(s.b));
    EXPECT_EQ(s.a, 1.0f);
  }
  EXPECT_NEAR(zero.r, facing.r, 1e-6);
  // Grazing light gives only the ambient term.
  EXPECT_NEAR(shade_iso(c, {1, 0, 0}, {0, 0, 1}).r, 0.5 * 0.25, 1e-6);
}

namespace {
// Uniform slab: every voxel has coverage a (colour white).
VolumeData uniform_volume(std::uint8_t a, Vec3 spacing, std::int64_t nz) {
  VolumeData v;
  v.geometry.dims = {4, 4, nz};
  v.geometry.spacing_mm = spacing;
  v.rgba.assign(std::size_t(16 * nz) * 4, 255);
  for (std::size_t i = 3; i < v.rgba.size(); i += 4)
    v.rgba[i] = a;
  return v;
}
Camera looking_down_z(const VolumeData& v) {
  OrbitParams o;
  o.target = v.geometry.box().centre();
  o.elevation_deg = 89.9;
  o.orthographic = true;
  o.zoom = 20;  // a tiny central patch: every ray crosses the full depth
  Camera cam = orbit_camera(o, v.geometry.box(), 4, 4);
  cam.forward = {0, 0, 1};
  cam.right = {1, 0, 0};
  cam.up = {0, -1, 0};
  cam.eye = o.target - cam.forward * 100.0;
  cam.near_mm = 1;
  return cam;
}
}  // namespace

TEST(Reference, UniformSlabMatchesTheClosedFormWithAnisotropicSpacing) {
  // 10 slices of 1.5 mm: L = 15 mm, Δ0 = 1 mm (smallest spacing) -> 1 - (1 - a)^15.
  VolumeData v = uniform_volume(51, {1, 1, 1.5}, 10);
  Camera cam = looking_down_z(v);
  RenderParams params;
  double a = 51 / 255.0;
  for (double steps : {1.0, 2.0, 16.0}) {
    ImageF img = render_reference(v, cam, params, {steps, 1});
    // Float compositing and the 1e-5 early-termination threshold: 1e-4.
    EXPECT_NEAR(img.at(2, 2)[3], 1 - std::pow(1 - a, 15.0), 1e-4) << steps;
    EXPECT_NEAR(img.at(2, 2)[0], 1 - std::pow(1 - a, 15.0), 1e-4) << steps;
  }
}

TEST(Reference, OpacityZeroOneAndAboveOne) {
  VolumeData clear = uniform_volume(0, {1, 1, 1}, 6);
  Camera cam = looking_down_z(clear);
  RenderParams params;
  params.background = {0.1f, 0.2f, 0.3f, 1};
  ImageF img = render_reference(clear, cam, params, {4, 1});
  EXPECT_NEAR(img.at(1, 1)[2], 0.3, 1e-6);  // alpha 0: only the background
  VolumeData solid = uniform_volume(255, {1, 1, 1}, 6);
  img = render_reference(solid, cam, params, {4, 1});
  EXPECT_NEAR(img.at(1, 1)[0], 1.0, 1e-6);  // alpha 1: the first sample hides everything
  params.opacity = 1.0000001;               // alpha slightly above 1: clamped, no NaN
  img = render_reference(solid, cam, params, {4, 1});
  EXPECT_NEAR(img.at(1, 1)[0], 1.0, 1e-6);
  EXPECT_FALSE(std::isnan(img.at(1, 1)[1]));
}

TEST(Reference, HalvingTheStepLeavesTheImageUnchanged) {
  auto v = synthetic::make_synthetic();
  OrbitParams o;
  o.target = v->geometry.box().centre();
  o.azimuth_deg = 30;
  o.elevation_deg = 20;
  Camera cam = orbit_camera(o, v->geometry.box(), 64, 64);
  for (Mode m : {Mode::kColour, Mode::kCt, Mode::kLabels}) {
    RenderParams params;
    params.mode = m;
    params.opacity = m == Mode::kCt ? 0.3 : 0.6;
    params.label_colours = make_label_colours(v->label_table, 0.5);
    Image8 a = to_rgba8(render_reference(*v, cam, params, {2}));
    Image8 b = to_rgba8(render_reference(*v, cam, params, {4}));
    double psnr = psnr_rgb(a, b);
    // Opacity correction makes the step size a discretisation choice only; 40 dB is the
    // GL-vs-reference bar of docs/GOALS.md, so the reference itself must do better.
    EXPECT_GT(psnr, 40.0) << mode_name(m);
    const std::uint8_t black[3] = {0, 0, 0};
    EXPECT_GT(count_non_background(a, black), 64 * 64 / 10) << mode_name(m);
    // Without opacity correction (the raw alpha per sample) the image changes a lot.
    if (m == Mode::kColour) {
      RenderParams raw = params;
      raw.opacity = params.opacity * 2;  // what halving Δ without correction amounts to
      EXPECT_LT(psnr_rgb(a, to_rgba8(render_reference(*v, cam, raw, {2}))), 35.0);
    }
  }
}

// The benchmark's quality measure (docs/BENCHMARKS.md, 'Viewer: bricks paged by view'): the
// background shared by both images must not count.
TEST(ForegroundDiff, LeavesTheSharedBackgroundOutAndCountsEitherImagesPixels) {
  Image8 a(10, 10), b(10, 10);  // black: background everywhere
  EXPECT_TRUE(std::isinf(diff_foreground(a, b).psnr_db));
  EXPECT_EQ(diff_foreground(a, b).pixels, 0);
  // 4 pixels lit in a only, 4 lit in both with an error of 10 in R.
  for (int i = 0; i < 4; ++i) {
    a.rgba[4 * i + 1] = 50;
    a.rgba[4 * (50 + i)] = 110;
    b.rgba[4 * (50 + i)] = 100;
  }
  const ForegroundDiff d = diff_foreground(a, b);
  EXPECT_EQ(d.pixels, 8);
  EXPECT_EQ(d.max_diff, 50);
  const double mse = (4 * 50.0 * 50.0 + 4 * 10.0 * 10.0) / (8 * 3);
  EXPECT_NEAR(d.psnr_db, 10 * std::log10(255.0 * 255.0 / mse), 1e-9);
  // Over the whole frame the 92 identical background pixels raise the PSNR by 10 log10(100 / 8).
  EXPECT_NEAR(psnr_rgb(a, b) - d.psnr_db, 10 * std::log10(100.0 / 8.0), 1e-9);
  // Another background colour: black pixels are then foreground.
  const std::uint8_t grey[3] = {7, 7, 7};
  EXPECT_EQ(diff_foreground(a, b, grey).pixels, 100);
  EXPECT_THROW(diff_foreground(a, Image8(5, 5)), std::invalid_argument);
}

TEST(Reference, IsoOnAUniformVolumeIsFinite) {
  VolumeData v;
  v.geometry.dims = {4, 4, 4};
  v.ct.assign(64, 500);  // above the threshold everywhere: zero gradient
  OrbitParams o;
  o.target = v.geometry.box().centre();
  Camera cam = orbit_camera(o, v.geometry.box(), 8, 8);
  RenderParams params;
  params.mode = Mode::kIso;
  params.iso_hu = 300;
  ImageF img = render_reference(v, cam, params);
  for (float f : img.rgba)
    EXPECT_TRUE(std::isfinite(f));
  EXPECT_GT(img.at(4, 4)[0], 0.5f);  // hit, shaded as facing the viewer
}

TEST(Reference, CameraInsideTheVolumeRenders) {
  auto v = synthetic::make_synthetic();
  OrbitParams o;
  o.target = v->geometry.box().centre();
  o.distance_mm = 2.0;
  Camera cam = orbit_camera(o, v->geometry.box(), 32, 32);
  RenderParams params;
  ImageF img = render_reference(*v, cam, params);
  for (float f : img.rgba)
    ASSERT_TRUE(std::isfinite(f));
  EXPECT_GT(img.at(16, 16)[3], 0.1f);
}

// Brick paging without GL: the bordered brick reader, the brick plan (tiling, visibility order,
// conservative empty-space skipping), lost slices, the isosurface bisection and the 2-D
// transfer function / label shading formulas.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>
#include <memory>
#include <random>

#include "packed_volume.h"
#include "synthetic_volume.h"
#include "vispack/format/writer.h"
#include "vispack/render/brick_reader.h"
#include "vispack/render/brick_tree.h"
#include "vispack/render/lost_slices.h"
#include "vispack/render/reference.h"

using namespace vispack;
using namespace vispack::render;

namespace {

std::filesystem::path temp_dir() {
  auto d = std::filesystem::path(::testing::TempDir()) /
           ("vispack_render_bricks_" + std::to_string(getpid()));
  std::filesystem::create_directories(d);
  return d;
}

std::shared_ptr<const VolumeSource> packed(const VolumeData& v, int edge, const std::string& name) {
  std::string path = (temp_dir() / name).string();
  vispack::test::write_packed_volume(path, v, edge);
  return open_packed(path);
}

Camera view(const Box3& box, double az, double el, double zoom, int size = 128) {
  OrbitParams o;
  o.target = box.centre();
  o.azimuth_deg = az;
  o.elevation_deg = el;
  o.zoom = zoom;
  return orbit_camera(o, box, size, size);
}

// Ray–box entry and exit, or false.
bool hit(const Box3& b, const Ray& r, double& t0, double& t1) {
  t0 = -1e300;
  t1 = 1e300;
  for (int a = 0; a < 3; ++a) {
    if (std::fabs(r.direction[a]) < 1e-300) {
      if (r.origin[a] < b.lo[a] || r.origin[a] > b.hi[a]) return false;
      continue;
    }
    double ta = (b.lo[a] - r.origin[a]) / r.direction[a],
           tb = (b.hi[a] - r.origin[a]) / r.direction[a];
    t0 = std::max(t0, std::min(ta, tb));
    t1 = std::min(t1, std::max(ta, tb));
  }
  return t1 > t0 + 1e-9;
}

}  // namespace

TEST(BorderedBrickReader, EqualsTheClampedWholeLevel) {
  auto v = synthetic::make_synthetic(21, 18, 13);  // not multiples of the brick edge
  MemorySource src(v, 8);
  BorderedBrickReader reader(src, 2, std::int64_t(64) << 20);
  const auto grid = brick_grid(src, 0);
  for (std::int64_t bz = 0; bz < grid[2]; ++bz)
    for (std::int64_t by = 0; by < grid[1]; ++by)
      for (std::int64_t bx = 0; bx < grid[0]; ++bx)
        for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels}) {
          BorderedBrick b = reader.read(c, {0, {bx, by, bz}});
          const int bpv = channel_bytes(c);
          const std::uint8_t* whole =
              c == Channel::kRgba
                  ? v->rgba.data()
                  : (c == Channel::kCt ? reinterpret_cast<const std::uint8_t*>(v->ct.data())
                                       : reinterpret_cast<const std::uint8_t*>(v->labels.data()));
          std::int64_t bad = 0;
          for (std::int64_t z = 0; z < b.dims[2]; ++z)
            for (std::int64_t y = 0; y < b.dims[1]; ++y)
              for (std::int64_t x = 0; x < b.dims[0]; ++x) {
                std::int64_t gx = std::clamp<std::int64_t>(b.offset[0] + x, 0, 20),
                             gy = std::clamp<std::int64_t>(b.offset[1] + y, 0, 17),
                             gz = std::clamp<std::int64_t>(b.offset[2] + z, 0, 12);
                const std::uint8_t* want = whole + bpv * v->index(gx, gy, gz);
                const std::uint8_t* got =
                    b.data.data() + bpv * (x + b.dims[0] * (y + b.dims[1] * z));
                if (std::memcmp(want, got, std::size_t(bpv)) != 0) ++bad;
              }
          ASSERT_EQ(bad, 0) << bx << " " << by << " " << bz << " " << channel_name(c);
        }
  // Each stored brick decoded once per channel (the cache holds them all).
  EXPECT_EQ(reader.decoded(), 3 * grid[0] * grid[1] * grid[2]);
}

TEST(BrickPlan, TilesTheVolumeAndOrdersBricksBackToFront) {
  auto v = synthetic::make_synthetic(44, 36, 28);
  auto src = packed(*v, 8, "plan.vpk");
  BrickTree tree(*src);
  const Box3 box = tree.volume_box();
  std::mt19937 rng(7);
  for (double zoom : {0.3, 1.0, 4.0})
    for (double az : {0.0, 30.0, 90.0, 200.0})
      for (bool ortho : {false, true}) {
        Camera cam = view(box, az, az == 0.0 ? 0.0 : 25.0, zoom);
        cam.orthographic = ortho;
        RenderParams p;
        p.mode = Mode::kMip;  // nothing skipped
        BrickPlan plan = plan_bricks(tree, cam, p, PlanOptions{}, channels_for(p, 7));
        ASSERT_FALSE(plan.draw.empty());
        EXPECT_EQ(plan.skipped, 0);
        // Tiling: drawn boxes do not overlap, and with culled ones they fill the volume.
        double drawn = 0;
        for (std::size_t i = 0; i < plan.draw.size(); ++i) {
          Box3 a = tree.brick_box(plan.draw[i]);
          Vec3 s = a.size();
          drawn += s.x * s.y * s.z;
          for (std::size_t j = i + 1; j < plan.draw.size(); ++j) {
            Box3 b = tree.brick_box(plan.draw[j]);
            Vec3 lo = max(a.lo, b.lo), hi = min(a.hi, b.hi);
            bool overlap = hi.x > lo.x + 1e-9 && hi.y > lo.y + 1e-9 && hi.z > lo.z + 1e-9;
            ASSERT_FALSE(overlap) << i << " " << j;
          }
        }
        Vec3 s = box.size();
        if (plan.culled == 0) {
          EXPECT_NEAR(drawn, s.x * s.y * s.z, 1e-6 * s.x * s.y * s.z);
        }
        // Visibility: along any pixel ray, the bricks it crosses come in the draw list in
        // decreasing distance (back to front).
        std::uniform_real_distribution<double> px(0, 128);
        for (int r = 0; r < 200; ++r) {
          Ray ray = cam.ray(px(rng), px(rng));
          double last_t = std::numeric_limits<double>::infinity();
          for (const BrickKey& k : plan.draw) {
            double t0, t1;
            if (!hit(tree.brick_box(k), ray, t0, t1)) continue;
            ASSERT_LE(t0, last_t + 1e-9) << "zoom " << zoom << " az " << az << " ortho " << ortho;
            last_t = t0;
          }
        }
      }
}

TEST(BrickPlan, SkipsOnlyBricksThatCannotContribute) {
  auto v = synthetic::make_synthetic(44, 36, 28);
  auto src = packed(*v, 8, "skip.vpk");
  BrickTree tree(*src);
  const LevelGeometry g = tree.level(0);
  Camera cam = view(tree.volume_box(), 30, 20, 1.0);
  for (int c = 0; c < 3; ++c) {
    RenderParams p;
    p.label_colours = make_label_colours(src->labels(), 0.5);
    if (c == 0) {
      p.mode = Mode::kIso;
      p.iso_hu = 500;
    } else if (c == 1) {
      p.mode = Mode::kLabels;
      p.highlight_label = 3;
      p.dim_factor = 0;
    } else {
      p.mode = Mode::kCt;
      p.window_center_hu = 600;
      p.window_width_hu = 200;
    }
    PlanOptions o;
    o.coarsest_level = 0;
    BrickPlan plan = plan_bricks(tree, cam, p, o, channels_for(p, 7));
    EXPECT_GT(plan.skipped, 0) << c;
    // Brute force: every skipped brick's voxels, with a 2-voxel border, give nothing visible.
    std::vector<bool> drawn(std::size_t(tree.grid(0)[0] * tree.grid(0)[1] * tree.grid(0)[2]));
    for (const BrickKey& k : plan.draw)
      drawn[std::size_t(k.brick[0] +
                        tree.grid(0)[0] * (k.brick[1] + tree.grid(0)[1] * k.brick[2]))] = true;
    for (std::int64_t i = 0; i < std::int64_t(drawn.size()); ++i) {
      if (drawn[std::size_t(i)]) continue;
      std::array<std::int64_t, 3> b{i % tree.grid(0)[0], (i / tree.grid(0)[0]) % tree.grid(0)[1],
                                    i / (tree.grid(0)[0] * tree.grid(0)[1])};
      for (std::int64_t z = b[2] * 8 - 2; z < b[2] * 8 + 10; ++z)
        for (std::int64_t y = b[1] * 8 - 2; y < b[1] * 8 + 10; ++y)
          for (std::int64_t x = b[0] * 8 - 2; x < b[0] * 8 + 10; ++x) {
            std::int64_t idx = v->index(std::clamp<std::int64_t>(x, 0, g.dims[0] - 1),
                                        std::clamp<std::int64_t>(y, 0, g.dims[1] - 1),
                                        std::clamp<std::int64_t>(z, 0, g.dims[2] - 1));
            const bool ok = c == 0   ? v->ct[std::size_t(idx)] < 500
                            : c == 1 ? v->labels[std::size_t(idx)] != 3
                                     : v->ct[std::size_t(idx)] <= 500;
            ASSERT_TRUE(ok) << "case " << c << ": a skipped brick holds a visible voxel";
          }
    }
  }
}

TEST(BrickTree, CoarseFirstReadsTheCoarsestLevelThenBuildsTheEagerTree) {
  // docs/BENCHMARKS.md, 'Viewer on long files': a kCoarseFirst tree reads the stats of the
  // coarsest level's bricks only and plans that level only; built in small steps it becomes the
  // eager tree (every range, every plan). With and without lost slices (whose bricks' stats are
  // computed from the filled data).
  auto v = synthetic::make_synthetic(44, 36, 28);
  std::shared_ptr<const VolumeSource> plain = packed(*v, 8, "lazy.vpk");
  std::shared_ptr<const VolumeSource> lost =
      std::make_shared<LostSliceSource>(plain, std::vector<std::int64_t>{9, 10, 21});
  for (const auto& src : {plain, lost}) {
    BrickTree eager(*src);
    BrickTree lazy(*src, TreeBuild::kCoarseFirst);
    const int top = eager.levels() - 1;
    ASSERT_GE(top, 3);
    const auto& gt = eager.grid(top);
    EXPECT_FALSE(lazy.complete());
    for (int l = 0; l < top; ++l)
      EXPECT_EQ(lazy.stats_reads(l), 0) << "level " << l;
    EXPECT_EQ(lazy.stats_reads(top), gt[0] * gt[1] * gt[2]);
    EXPECT_EQ(eager.stats_reads(top), 0);  // the eager tree ranges level 0's stats only
    RenderParams p;
    p.label_colours = make_label_colours(src->labels(), 0.5);
    const Camera cam = view(eager.volume_box(), 30, 20, 3.0);
    const unsigned ch = channels_for(p, eager.present_channels());
    const BrickPlan first = plan_bricks(lazy, cam, p, PlanOptions{}, ch);
    ASSERT_FALSE(first.draw.empty());
    for (const BrickKey& k : first.draw)
      EXPECT_EQ(k.level, top);
    int steps = 0;
    double progress = lazy.build_progress();
    EXPECT_EQ(progress, 0.0);
    while (!lazy.build_step(7)) {
      ++steps;
      EXPECT_GT(lazy.build_progress(), progress);
      progress = lazy.build_progress();
      EXPECT_LT(progress, 1.0);
    }
    EXPECT_EQ(lazy.build_progress(), 1.0);
    const auto& g0 = eager.grid(0);
    EXPECT_GT(steps, g0[0] * g0[1] * g0[2] / 7 - 1);  // small steps, as asked
    EXPECT_EQ(lazy.stats_reads(0), g0[0] * g0[1] * g0[2]);
    // Every brick's ranges: the same skipping decisions in every mode.
    std::vector<RenderParams> cases(5, p);
    cases[0].mode = Mode::kColour;
    cases[1].mode = Mode::kIso;
    cases[1].iso_hu = 500;
    cases[2].mode = Mode::kLabels;
    cases[2].highlight_label = 3;
    cases[2].dim_factor = 0;
    cases[3].mode = Mode::kCt;
    cases[3].window_center_hu = 600;
    cases[3].window_width_hu = 200;
    cases[4].mode = Mode::kIso;
    cases[4].iso_hu = 30;
    std::int64_t skipped = 0;
    for (int l = 0; l <= top; ++l) {
      const auto& g = eager.grid(l);
      for (std::int64_t z = 0; z < g[2]; ++z)
        for (std::int64_t y = 0; y < g[1]; ++y)
          for (std::int64_t x = 0; x < g[0]; ++x)
            for (const RenderParams& c : cases) {
              const bool e = eager.may_contribute({l, {x, y, z}}, c);
              skipped += !e;
              ASSERT_EQ(lazy.may_contribute({l, {x, y, z}}, c), e)
                  << "level " << l << " brick " << x << "," << y << "," << z << " "
                  << mode_name(c.mode);
            }
    }
    EXPECT_GT(skipped, 0);  // the cases do skip bricks
    // Plans: ideal, under a byte budget, with a partly resident cache.
    for (const RenderParams& c : cases)
      for (double zoom : {1.0, 4.0}) {
        const Camera cc = view(eager.volume_box(), 70, -15, zoom);
        PlanOptions o;
        o.max_bytes = zoom > 1 ? 200000 : 0;
        const unsigned cch = channels_for(c, eager.present_channels());
        const ResidentFn resident = [](const BrickKey& k) { return k.level >= 1; };
        for (const ResidentFn* r : {static_cast<const ResidentFn*>(nullptr), &resident}) {
          const BrickPlan a = plan_bricks(eager, cc, c, o, cch, r ? *r : ResidentFn{});
          const BrickPlan b = plan_bricks(lazy, cc, c, o, cch, r ? *r : ResidentFn{});
          EXPECT_TRUE(a.draw == b.draw) << mode_name(c.mode) << " zoom " << zoom;
          EXPECT_TRUE(a.missing == b.missing) << mode_name(c.mode) << " zoom " << zoom;
          EXPECT_EQ(a.skipped, b.skipped);
          EXPECT_EQ(a.culled, b.culled);
          EXPECT_EQ(a.bytes, b.bytes);
          EXPECT_EQ(a.lod_pixels, b.lod_pixels);
        }
      }
  }
}

TEST(LostSlices, InterpolatedFromTheNearestValidSlices) {
  auto v = std::make_shared<VolumeData>();
  v->geometry.dims = {3, 2, 8};
  v->rgba.resize(4 * 48);
  for (int z = 0; z < 8; ++z)
    for (int i = 0; i < 6; ++i) {
      std::uint8_t* p = &v->rgba[std::size_t(4 * (z * 6 + i))];
      p[0] = std::uint8_t(20 * z + i);
      p[1] = std::uint8_t(10 * z);
      p[2] = 7;
      p[3] = 255;
    }
  auto mem = std::make_shared<MemorySource>(v, 4);
  LostSliceSource src(mem, {0, 3, 4, 99});  // 99 is outside: ignored
  std::vector<std::uint8_t> out(4 * 48);
  Region all;
  all.size = {3, 2, 8};
  src.read_region(Channel::kRgba, 0, all, out.data());
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(out[std::size_t(4 * i)], v->rgba[std::size_t(4 * (6 + i))]);  // z 0 copies z 1
    // z 3 and 4 between the valid 2 and 5: 1/3 and 2/3 of the way.
    EXPECT_EQ(out[std::size_t(4 * (18 + i))], std::uint8_t(std::lround(40 + i + 60.0 / 3)));
    EXPECT_EQ(out[std::size_t(4 * (24 + i)) + 1], std::uint8_t(std::lround(20 + 30.0 * 2 / 3)));
    EXPECT_EQ(out[std::size_t(4 * (30 + i))], v->rgba[std::size_t(4 * (30 + i))]);  // valid
  }
  // A region holding only lost slices reads its neighbours from the source.
  Region one;
  one.offset = {0, 0, 4};
  one.size = {3, 2, 1};
  std::vector<std::uint8_t> slice(24);
  src.read_region(Channel::kRgba, 0, one, slice.data());
  EXPECT_TRUE(std::equal(slice.begin(), slice.end(), out.begin() + 4 * 24));
  EXPECT_EQ(lost_slices_at_level({3, 4, 9}, 1, 4), (std::vector<std::int64_t>{1, 2}));
}

TEST(Iso, BisectionFindsTheCrossingThatLinearInterpolationMisses) {
  // HU = 10·x² sampled at integer x: trilinear sampling makes it piecewise linear; a bracket
  // spanning three voxels is refined into one cell, where the crossing is exact.
  VolumeData v;
  v.geometry.dims = {16, 1, 1};
  v.ct.resize(16);
  for (int x = 0; x < 16; ++x)
    v.ct[std::size_t(x)] = std::int16_t(10 * x * x);
  VolumeSampler s(v);
  Ray ray{{0, 0, 0}, {1, 0, 0}};
  const double iso = 400;  // between x = 6 (360) and 7 (490): 6 + 40/130
  const double truth = 6 + 40.0 / 130.0;
  double ta = 4.2, tb = 7.9;
  double fa = s.hu(ray.origin + ray.direction * ta), fb = s.hu(ray.origin + ray.direction * tb);
  double linear = ta + (tb - ta) * (iso - fa) / (fb - fa);
  double refined = refine_iso(s, ray, iso, ta, fa, tb, fb);
  EXPECT_NEAR(refined, truth, 1e-9);
  EXPECT_GT(std::fabs(linear - truth), 0.1);
}

TEST(Tf2d, TableLookupsAndSkipping) {
  Tf2dWidget w;
  w.value_lo = 0;
  w.value_hi = 1000;
  w.gradient_lo = 100;
  w.gradient_hi = 400;
  w.colour = {1, 0.5f, 0.25f, 0.8f};
  TransferFunction2D tf = make_tf2d({w}, -1000, 2000, 400);
  Rgba peak = tf.sample(500, 200);  // tent peak at the widget's centre
  EXPECT_NEAR(peak.a, 0.8, 0.03);
  EXPECT_FLOAT_EQ(peak.r, 1.0f);
  EXPECT_EQ(tf.sample(500, 0).a, 0.0f);  // below the gradient range
  EXPECT_EQ(tf.sample(-800, 200).a, 0.0f);
  EXPECT_FALSE(tf.any_opacity(-1000, -100));
  EXPECT_TRUE(tf.any_opacity(-1000, 100));
  EXPECT_TRUE(tf.any_opacity(400, 600));
  EXPECT_FALSE(tf.any_opacity(1100, 2000));
}

TEST(LabelShading, ModulatedAndRamp) {
  Rgba c{0.8f, 0.4f, 0.2f, 0.5f};
  Rgba m = shade_label(c, LabelShading::kModulated, 0.5);
  EXPECT_FLOAT_EQ(m.r, 0.8f * 0.75f);  // k + (1 - k)·t with k = 0.5
  EXPECT_FLOAT_EQ(shade_label(c, LabelShading::kModulated, 0.0).g, 0.4f * 0.5f);
  EXPECT_FLOAT_EQ(m.a, 0.5f);
  Rgba r0 = shade_label(c, LabelShading::kRamp, 0.0), r1 = shade_label(c, LabelShading::kRamp, 0.5),
       r2 = shade_label(c, LabelShading::kRamp, 1.0);
  EXPECT_FLOAT_EQ(r0.r, 0.0f);
  EXPECT_FLOAT_EQ(r1.g, 0.4f);
  EXPECT_FLOAT_EQ(r2.b, 1.0f);
  EXPECT_FLOAT_EQ(shade_label(c, LabelShading::kFlat, 0.1).r, 0.8f);
}

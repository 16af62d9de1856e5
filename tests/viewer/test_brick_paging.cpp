// Brick-paged rendering (docs/BENCHMARKS.md, 'Viewer: bricks paged by view') against the
// whole-level renderer and the CPU reference: the bricked frame of one level equals the whole-level
// frame of that level (no seams, skipping changes nothing); frames whose level follows the screen
// footprint match the reference of the levels they draw; empty bricks are neither uploaded nor
// drawn; lost slices never show as a black band; the labels shading and the 2-D transfer function
// match the reference. Comparisons are over the foreground (body_diff.h) with a maximum-difference
// bound.
#include <gtest/gtest.h>
#include <unistd.h>

#include <OpenImageIO/imageio.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <vector>

#include "../render/synthetic_volume.h"
#include "body_diff.h"
#include "test_support.h"
#include "viewer_test_support.h"
#include "vispack/format/writer.h"
#include "vispack/render/brick_tree.h"
#include "vispack/render/lost_slices.h"
#include "vispack/render/reference.h"
#include "vispack/viewer/app.h"
#include "vispack/viewer/brick_cache.h"
#include "vispack/viewer/context.h"
#include "vispack/viewer/slice_renderer.h"

using namespace vispack;
using namespace vispack::render;
using vispack::test::BodyDiff;
using vispack::test::diff_in_body;
using vispack::viewer::BrickCache;
using vispack::viewer::HeadlessContext;
using vispack::viewer::SliceRenderer;
using vispack::viewer::VolumeTextures;

namespace {

std::vector<char*> g_argv;

class Bricks : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    context_ = vispack::test::make_gl_context(g_argv);
    if (!context_) return;
    dir_ = std::filesystem::path(::testing::TempDir()) /
           ("vispack_bricks_" + std::to_string(getpid()));
    std::filesystem::create_directories(dir_);
    // 44x36x28 with bricks of 8: not multiples of the brick edge; levels 44, 22, 11 (the level
    // boxes coincide because the dims halve exactly down to level 2).
    original_ = synthetic::make_synthetic(44, 36, 28);
    path_ = (dir_ / "bricks.vpk").string();
    vispack::test::write_packed_volume(path_, *original_, 8);
    source_ = open_packed(path_);
    tree_ = std::make_unique<BrickTree>(*source_);
    renderer_ = std::make_unique<SliceRenderer>();
    cache_ = std::make_unique<BrickCache>(*source_, std::int64_t(256) << 20, 2);
  }
  static void TearDownTestSuite() {
    cache_.reset();
    renderer_.reset();
    tree_.reset();
    source_.reset();
    context_.reset();
    if (!dir_.empty()) std::filesystem::remove_all(dir_);
  }
  void SetUp() override { ASSERT_TRUE(context_) << "no OpenGL context (EGL and xvfb-run failed)"; }

  static Camera camera(int size = 128, double az = 30, double el = 20, double zoom = 1) {
    OrbitParams o;
    Box3 box = source_->level(0).box();
    o.target = box.centre();
    o.azimuth_deg = az;
    o.elevation_deg = el;
    o.zoom = zoom;
    return orbit_camera(o, box, size, size);
  }
  static RenderParams params(Mode m) {
    RenderParams p;
    p.mode = m;
    p.label_colours = make_label_colours(source_->labels(), 0.5);
    p.opacity = m == Mode::kCt ? 0.3 : 0.6;
    p.window_center_hu = 300;
    p.window_width_hu = 1600;
    p.iso_hu = -200;
    p.mpr_target = source_->level(0).box().centre();
    p.reference_length_mm = reference_length(source_->level(0));
    Tf2dWidget w;
    w.value_lo = -300;
    w.value_hi = 900;
    w.gradient_lo = 20;
    w.gradient_hi = 400;
    w.colour = {0.9f, 0.7f, 0.4f, 0.5f};
    p.tf2d = make_tf2d({w});
    return p;
  }
  // Loads every brick of `plan` and renders it.
  static Image8 bricked(const BrickPlan& plan, const Camera& cam, const RenderParams& p) {
    unsigned ch = channels_for(p, tree_->present_channels());
    cache_->request(plan.draw, ch);
    cache_->pump(-1);
    cache_->use(plan.draw);
    renderer_->render_bricks(*cache_, *tree_, plan, cam, p);
    return renderer_->read_rgba8();
  }
  static BrickPlan plan_level(int level, const Camera& cam, const RenderParams& p) {
    PlanOptions o;
    o.finest_level = o.coarsest_level = level;
    return plan_bricks(*tree_, cam, p, o, channels_for(p, tree_->present_channels()));
  }

  static inline std::unique_ptr<HeadlessContext> context_;
  static inline std::filesystem::path dir_;
  static inline std::shared_ptr<VolumeData> original_;
  static inline std::string path_;
  static inline std::shared_ptr<const VolumeSource> source_;
  static inline std::unique_ptr<BrickTree> tree_;
  static inline std::unique_ptr<SliceRenderer> renderer_;
  static inline std::unique_ptr<BrickCache> cache_;
};

}  // namespace

TEST_F(Bricks, BrickedFrameEqualsTheWholeLevelFrame) {
  // Same lattice, same samples (brick borders), skipped bricks contribute nothing: the bricked
  // frame of a level is the whole-level frame of that level up to float rounding.
  for (int level : {0, 1}) {
    VolumeTextures whole;
    whole.upload(*source_, level, 2);
    for (Mode m : {Mode::kColour, Mode::kCt, Mode::kMip, Mode::kAverage, Mode::kIso, Mode::kLabels,
                   Mode::kMpr, Mode::kTf2d}) {
      for (double az : {30.0, 90.0}) {
        Camera cam = camera(96, az, az == 90.0 ? 0.0 : 20.0);
        RenderParams p = params(m);
        BrickPlan plan = plan_level(level, cam, p);
        Image8 b = bricked(plan, cam, p);
        renderer_->render(whole, cam, p);
        Image8 w = renderer_->read_rgba8();
        BodyDiff d = diff_in_body(b, w);
        std::cout << "level " << level << " " << mode_name(m) << " az " << az << ": "
                  << plan.draw.size() << " bricks drawn, " << plan.skipped << " skipped; PSNR "
                  << d.psnr << " dB, max diff " << d.max_diff << ", body " << d.body << "\n";
        EXPECT_GT(d.body, 96 * 96 / 20) << mode_name(m);
        EXPECT_GE(d.psnr, 50.0) << level << " " << mode_name(m) << " " << az;
        // Iso and mpr pixels exactly on a brick face may land in either brick: still one sample.
        EXPECT_LE(d.max_diff, m == Mode::kIso ? 24 : 3)
            << level << " " << mode_name(m) << " " << az;
      }
    }
  }
}

TEST_F(Bricks, SkippingEmptyBricksChangesNoPixel) {
  // Cases where many bricks are skipped: the bricked frame still equals the whole-level one.
  VolumeTextures whole;
  whole.upload(*source_, 0, 2);
  Camera cam = camera(96);
  for (int c = 0; c < 3; ++c) {
    RenderParams p = params(c == 0 ? Mode::kIso : (c == 1 ? Mode::kLabels : Mode::kColour));
    if (c == 0) p.iso_hu = 500;  // the bone only
    if (c == 1) {                // label 3 only
      p.highlight_label = 3;
      p.dim_factor = 0;
    }
    if (c == 2) {  // colour, opacity from a bone window
      p.opacity_source = OpacitySource::kCt;
      p.window_center_hu = 600;
      p.window_width_hu = 200;
    }
    BrickPlan plan = plan_level(0, cam, p);
    Image8 b = bricked(plan, cam, p);
    renderer_->render(whole, cam, p);
    BodyDiff d = diff_in_body(b, renderer_->read_rgba8());
    std::cout << mode_name(p.mode) << ": " << plan.skipped << " of "
              << plan.skipped + std::int64_t(plan.draw.size()) << " bricks skipped; PSNR " << d.psnr
              << " dB, max diff " << d.max_diff << ", body " << d.body << "\n";
    EXPECT_GT(plan.skipped, 10);
    EXPECT_GT(d.body, 50);
    EXPECT_GE(d.psnr, 50.0);
    EXPECT_LE(d.max_diff, 3);
  }
}

TEST_F(Bricks, LevelFollowsTheScreenFootprintAndMatchesTheReference) {
  // Near: voxels cover about a pixel, level 0 everywhere; far (zoom 0.25): a voxel covers a
  // quarter pixel, so coarser levels. Each frame is compared with the reference of the level
  // it draws (all bricks of one level here).
  for (double zoom : {1.0, 0.25}) {
    Camera cam = camera(128, 30, 20, zoom);
    RenderParams p = params(Mode::kColour);
    PlanOptions o;
    BrickPlan plan = plan_bricks(*tree_, cam, p, o, channels_for(p, tree_->present_channels()));
    ASSERT_FALSE(plan.draw.empty());
    int lo = 99, hi = -1;
    for (const BrickKey& k : plan.draw) {
      lo = std::min(lo, k.level);
      hi = std::max(hi, k.level);
    }
    std::cout << "zoom " << zoom << ": levels " << lo << ".." << hi << ", " << plan.draw.size()
              << " bricks, " << plan.skipped << " skipped, " << plan.culled << " culled\n";
    if (zoom == 1.0) {
      EXPECT_EQ(hi, 0);
    } else {
      EXPECT_GE(lo, 1);
    }
    ASSERT_EQ(lo, hi) << "this camera sees the whole volume at one footprint";
    Image8 gl = bricked(plan, cam, p);
    VolumeData level = load_level(*source_, lo);
    Image8 ref = to_rgba8(render_reference(level, cam, p, {16}));
    BodyDiff d = diff_in_body(gl, ref);
    std::cout << "  vs reference of level " << lo << ": PSNR " << d.psnr << " dB, max diff "
              << d.max_diff << "\n";
    EXPECT_GE(d.psnr, 40.0);
    EXPECT_LE(d.max_diff, 8);
  }
}

TEST_F(Bricks, ZoomingInShowsLevel0WhereTheScreenNeedsIt) {
  // Camera close to one corner, wide field: near bricks at level 0, far ones coarser.
  Camera cam = camera(128, 30, 20, 4.0);
  RenderParams p = params(Mode::kColour);
  BrickPlan plan =
      plan_bricks(*tree_, cam, p, PlanOptions{}, channels_for(p, tree_->present_channels()));
  int count[3] = {0, 0, 0};
  for (const BrickKey& k : plan.draw)
    count[k.level]++;
  std::cout << "zoom 4: " << count[0] << " / " << count[1] << " / " << count[2]
            << " bricks of level 0 / 1 / 2, " << plan.culled << " culled\n";
  EXPECT_GT(count[0], 0);
  EXPECT_GT(plan.culled, 0);  // zoomed in: part of the volume is off screen
  // Mixed levels composite into one integral: against the level-0 reference within what the
  // coarser far bricks lose.
  Image8 gl = bricked(plan, cam, p);
  VolumeData level0 = load_level(*source_, 0);
  BodyDiff d = diff_in_body(gl, to_rgba8(render_reference(level0, cam, p, {16})));
  std::cout << "  vs level-0 reference: PSNR " << d.psnr << " dB, max diff " << d.max_diff << "\n";
  EXPECT_GE(d.psnr, 30.0);

  // Coarser where a voxel may cover 3 pixels: a mix of levels in one frame. Against the level-0
  // reference it loses what the coarser levels lose (the silhouette moves by up to a coarse
  // voxel), and it must stay as close to it as the all-level-1 frame is.
  // A wide (90°) field close to the volume: depths from ~5 to ~50 mm.
  OrbitParams wide;
  wide.target = source_->level(0).box().centre();
  wide.azimuth_deg = 30;
  wide.elevation_deg = 20;
  wide.fov_y_deg = 90;
  wide.zoom = 2;
  cam = orbit_camera(wide, source_->level(0).box(), 64, 64);
  PlanOptions coarse;
  coarse.lod_pixels = 3;
  BrickPlan mixed = plan_bricks(*tree_, cam, p, coarse, channels_for(p, tree_->present_channels()));
  int levels_used = 0, per[4] = {0, 0, 0, 0};
  for (const BrickKey& k : mixed.draw)
    per[k.level]++;
  for (int n : per)
    levels_used += n > 0;
  std::cout << "lod 3: " << per[0] << " / " << per[1] << " / " << per[2] << " / " << per[3]
            << " bricks of level 0 / 1 / 2 / 3\n";
  EXPECT_GE(levels_used, 2);
  BodyDiff dm =
      diff_in_body(bricked(mixed, cam, p), to_rgba8(render_reference(level0, cam, p, {16})));
  BodyDiff d1 = diff_in_body(bricked(plan_level(1, cam, p), cam, p),
                             to_rgba8(render_reference(level0, cam, p, {16})));
  std::cout << "  mixed vs level-0 reference: PSNR " << dm.psnr << " dB, max diff " << dm.max_diff
            << "; all level 1: PSNR " << d1.psnr << " dB\n";
  EXPECT_GE(dm.psnr, 30.0);
  EXPECT_GE(dm.psnr, d1.psnr - 1.0);
}

TEST_F(Bricks, EmptyBricksAreNeitherUploadedNorDrawn) {
  Camera cam = camera(96);
  struct Case {
    Mode mode;
    double iso;
    int highlight;
    double dim;
  };
  // Colour with CT opacity and a bone window: only bone bricks. Iso above the soft tissue: only
  // bone bricks. Labels with only label 3 visible: the left half is skipped.
  for (Case c : {Case{Mode::kColour, 0, -1, 0.2}, Case{Mode::kIso, 500, -1, 0.2},
                 Case{Mode::kLabels, 0, 3, 0.0}, Case{Mode::kMip, 0, -1, 0.2}}) {
    RenderParams p = params(c.mode);
    p.iso_hu = c.mode == Mode::kIso ? c.iso : p.iso_hu;
    p.highlight_label = c.highlight;
    p.dim_factor = c.dim;
    if (c.mode == Mode::kColour) {
      p.opacity_source = OpacitySource::kCt;
      p.window_center_hu = 600;
      p.window_width_hu = 200;
    }
    BrickPlan plan = plan_level(0, cam, p);
    const std::int64_t total = tree_->grid(0)[0] * tree_->grid(0)[1] * tree_->grid(0)[2];
    std::cout << mode_name(c.mode) << ": " << plan.draw.size() << " drawn, " << plan.skipped
              << " skipped of " << total << "\n";
    EXPECT_EQ(std::int64_t(plan.draw.size()) + plan.skipped + plan.culled, total);
    if (c.mode == Mode::kMip) {
      EXPECT_EQ(plan.skipped, 0);  // every sample counts in a maximum
    } else {
      EXPECT_GT(plan.skipped, total / 10) << mode_name(c.mode);
    }
    // Nothing visible at all: every brick skipped, the frame is the background.
    if (c.mode == Mode::kIso) {
      p.iso_hu = 5000;
      BrickPlan none = plan_level(0, cam, p);
      EXPECT_TRUE(none.draw.empty());
      cache_->reset_counters();
      Image8 img = bricked(none, cam, p);
      const std::uint8_t black[3] = {0, 0, 0};
      EXPECT_EQ(count_non_background(img, black, 0), 0);
      EXPECT_EQ(cache_->stats().uploaded_bytes, 0);
    }
  }
}

TEST_F(Bricks, TheGpuBudgetHoldsAndThePlanCoarsensToFitIt) {
  const std::int64_t budget = 128 << 10;  // 128 KB: far less than level 0 (670 KB here)
  BrickCache cache(*source_, budget, 2);
  Camera cam = camera(96);
  RenderParams p = params(Mode::kColour);
  const unsigned ch = channels_for(p, tree_->present_channels());
  // Everything of level 0 asked for: the cache evicts as it goes and stays within the budget
  // (plus at most the brick being uploaded).
  BrickPlan all = plan_level(0, cam, p);
  ASSERT_GT(all.bytes, 4 * budget);
  cache.request(all.draw, ch);
  cache.pump(-1);
  const std::int64_t one = tree_->brick_bytes(all.draw[0], ch, BrickCache::kBorder);
  EXPECT_LE(cache.stats().resident_bytes, budget + one);
  EXPECT_GT(cache.stats().evicted, 0);
  // With the budget, the plan coarsens until its bricks fit, and then they all stay resident.
  PlanOptions o;
  o.max_bytes = budget;
  BrickPlan fit = plan_bricks(*tree_, cam, p, o, ch);
  std::cout << "budget " << budget << " B: plan of " << fit.draw.size() << " bricks, " << fit.bytes
            << " B, lod " << fit.lod_pixels << " px\n";
  EXPECT_LE(fit.bytes, budget);
  EXPECT_GT(fit.lod_pixels, 1.0);
  cache.request(fit.draw, ch);
  cache.pump(-1);
  cache.use(fit.draw);
  for (const BrickKey& k : fit.draw)
    EXPECT_TRUE(cache.resident(k, ch));
}

TEST_F(Bricks, CoarseBricksFirstThenRefinedAsTheyArrive) {
  // A fresh cache: the first plan asks for the coarsest brick only; each round uploads what the
  // plan misses; the drawn set always tiles the visible volume (no overlaps: the frame is a
  // valid picture at every round) and converges to the ideal plan.
  BrickCache cache(*source_, std::int64_t(256) << 20, 2);
  Camera cam = camera(128, 30, 20, 4.0);
  RenderParams p = params(Mode::kColour);
  unsigned ch = channels_for(p, tree_->present_channels());
  BrickPlan ideal = plan_bricks(*tree_, cam, p, PlanOptions{}, ch);
  ResidentFn resident = [&](const BrickKey& k) { return cache.resident(k, ch); };
  int rounds = 0;
  for (;; ++rounds) {
    BrickPlan plan = plan_bricks(*tree_, cam, p, PlanOptions{}, ch, resident);
    if (rounds == 0) {
      EXPECT_TRUE(plan.draw.empty());
      ASSERT_EQ(plan.missing.size(), 1u);
      EXPECT_EQ(plan.missing[0].level, tree_->levels() - 1);
    } else {
      cache.use(plan.draw);
      renderer_->render_bricks(cache, *tree_, plan, cam, p);
      Image8 img = renderer_->read_rgba8();
      // No overlap: an overlapped brick would double its opacity somewhere; the frame never
      // exceeds the ideal frame's coverage by more than the levels' averaging can explain.
      EXPECT_GT(count_non_background(img, std::array<std::uint8_t, 3>{0, 0, 0}.data()), 0);
    }
    if (plan.missing.empty()) {
      EXPECT_EQ(plan.draw.size(), ideal.draw.size());
      for (std::size_t i = 0; i < plan.draw.size() && i < ideal.draw.size(); ++i)
        EXPECT_TRUE(plan.draw[i] == ideal.draw[i]) << i;
      break;
    }
    ASSERT_LT(rounds, 10);
    cache.request(plan.missing, ch);
    cache.pump(-1);
  }
  EXPECT_EQ(rounds, tree_->levels());  // the coarsest brick, then one round per finer level
}

TEST_F(Bricks, CoarseFirstTreeDrawsTheCoarsestLevelFirstThenTheEagerImage) {
  // vispack-view's path on opening a file (docs/BENCHMARKS.md, 'Viewer on long files'): the
  // first picture is planned and drawn before any finer level's stats are read, and equals the
  // eager tree's picture of the coarsest level; once the tree is built, every frame (levels
  // following the screen footprint) equals the eager tree's, pixel for pixel.
  const int top = tree_->levels() - 1;
  ASSERT_GE(top, 2);
  auto differing = [](const Image8& a, const Image8& b) {  // bytes that differ
    if (a.rgba.size() != b.rgba.size()) return std::ptrdiff_t(-1);
    std::ptrdiff_t n = 0;
    for (std::size_t i = 0; i < a.rgba.size(); ++i)
      n += a.rgba[i] != b.rgba[i];
    return n;
  };
  BrickTree lazy(*source_, TreeBuild::kCoarseFirst);
  for (Mode m : {Mode::kColour, Mode::kIso, Mode::kLabels}) {
    const Camera cam = camera(96, 30, 20, 2.0);
    RenderParams p = params(m);
    const unsigned ch = channels_for(p, tree_->present_channels());
    BrickPlan first = plan_bricks(lazy, cam, p, PlanOptions{}, ch);
    for (const BrickKey& k : first.draw)
      EXPECT_EQ(k.level, top) << mode_name(m);
    for (int l = 0; l < top; ++l)
      EXPECT_EQ(lazy.stats_reads(l), 0) << "level " << l << " read before the first picture";
    EXPECT_FALSE(lazy.complete());
    cache_->request(first.draw, ch);
    cache_->pump(-1);
    cache_->use(first.draw);
    renderer_->render_bricks(*cache_, lazy, first, cam, p);
    const Image8 lazy_first = renderer_->read_rgba8();
    const Image8 eager_first = bricked(plan_level(top, cam, p), cam, p);
    EXPECT_GT(count_non_background(lazy_first, std::array<std::uint8_t, 3>{0, 0, 0}.data()), 0);
    EXPECT_EQ(differing(lazy_first, eager_first), 0) << mode_name(m) << ": first picture";
  }
  lazy.build_all();
  ASSERT_TRUE(lazy.complete());
  for (Mode m : {Mode::kColour, Mode::kIso, Mode::kLabels, Mode::kCt})
    for (double zoom : {1.0, 4.0}) {
      const Camera cam = camera(96, 60, 10, zoom);
      RenderParams p = params(m);
      const unsigned ch = channels_for(p, tree_->present_channels());
      BrickPlan settled = plan_bricks(lazy, cam, p, PlanOptions{}, ch);
      cache_->request(settled.draw, ch);
      cache_->pump(-1);
      cache_->use(settled.draw);
      renderer_->render_bricks(*cache_, lazy, settled, cam, p);
      const Image8 lazy_img = renderer_->read_rgba8();
      BrickPlan eager = plan_bricks(*tree_, cam, p, PlanOptions{}, ch);
      int finest = top;
      for (const BrickKey& k : settled.draw)
        finest = std::min(finest, k.level);
      if (zoom > 1) {
        EXPECT_LT(finest, top) << mode_name(m) << ": the settled frame is refined";
      }
      EXPECT_EQ(settled.draw.size(), eager.draw.size()) << mode_name(m);
      EXPECT_EQ(differing(lazy_img, bricked(eager, cam, p)), 0)
          << mode_name(m) << " zoom " << zoom << ": settled frame";
    }
}

TEST_F(Bricks, LostSlicesAreSampledAcrossNeverABlackBand) {
  // Slice 13 of the colour is black in the file and listed as lost; the viewer interpolates
  // slices 12 and 14. Truth: the original volume (smooth along z, so the interpolation is
  // close to it); the unfilled file shows a dark band.
  auto broken = std::make_shared<VolumeData>(*original_);
  const std::int64_t nx = broken->geometry.dims[0], ny = broken->geometry.dims[1];
  for (std::int64_t i = 0; i < nx * ny; ++i)
    for (int c = 0; c < 3; ++c)
      broken->rgba[std::size_t(4 * (13 * nx * ny + i) + c)] = 0;
  std::string path = (dir_ / "lost.vpk").string();
  vispack::test::write_packed_volume(path, *broken, 8, {{"slices", {{"black", {13}}}}});
  std::shared_ptr<const VolumeSource> raw = open_packed(path);
  ASSERT_EQ(raw->lost_slices(), std::vector<std::int64_t>{13});
  std::shared_ptr<const VolumeSource> filled = fill_lost_slices(raw);
  BrickTree tree(*filled);
  BrickCache cache(*filled, std::int64_t(64) << 20, 2);
  // Side view (along y) so that slice 13 crosses the frame.
  Camera cam = camera(96, 0, 0);
  RenderParams p = params(Mode::kColour);
  PlanOptions o;
  o.finest_level = o.coarsest_level = 0;
  unsigned ch = channels_for(p, tree.present_channels());
  BrickPlan plan = plan_bricks(tree, cam, p, o, ch);
  cache.request(plan.draw, ch);
  cache.pump(-1);
  renderer_->render_bricks(cache, tree, plan, cam, p);
  Image8 gl = renderer_->read_rgba8();
  Image8 truth = to_rgba8(render_reference(*original_, cam, p, {16}));
  Image8 band = to_rgba8(render_reference(*broken, cam, p, {16}));
  BodyDiff d = diff_in_body(gl, truth), b = diff_in_body(band, truth);
  std::cout << "filled vs original: PSNR " << d.psnr << " dB, max diff " << d.max_diff
            << "; unfilled: PSNR " << b.psnr << " dB, max diff " << b.max_diff << "\n";
  EXPECT_GE(d.psnr, 40.0);
  EXPECT_LE(d.max_diff, 12);
  EXPECT_GT(b.max_diff, 40);  // the band the viewer must not show
  // The reference of the filled source agrees with the GL frame (same data, same sampling).
  VolumeData level0 = load_level(*filled, 0);
  BodyDiff r = diff_in_body(gl, to_rgba8(render_reference(level0, cam, p, {16})));
  EXPECT_GE(r.psnr, 40.0);
  EXPECT_LE(r.max_diff, 8);
}

TEST_F(Bricks, LabelShadingAndTf2dMatchTheReference) {
  VolumeData level0 = load_level(*source_, 0);
  Camera cam = camera(96);
  struct Case {
    Mode mode;
    LabelShading shading;
  };
  for (Case c :
       {Case{Mode::kLabels, LabelShading::kModulated}, Case{Mode::kLabels, LabelShading::kRamp},
        Case{Mode::kTf2d, LabelShading::kFlat}, Case{Mode::kIso, LabelShading::kFlat}}) {
    // At 2 slices per voxel the ramp (twice the intensity slope of modulated) and the
    // gradient-driven 2-D transfer function carry more sampling error; halving the slice
    // spacing must bring the frame closer to the reference (a formula mismatch would not).
    double psnr[2];
    for (int i = 0; i < 2; ++i) {
      RenderParams p = params(c.mode);
      p.label_shading = c.shading;
      p.opacity = 0.8;
      p.slices_per_voxel = i == 0 ? 2 : 4;
      Image8 gl = bricked(plan_level(0, cam, p), cam, p);
      Image8 ref = to_rgba8(render_reference(level0, cam, p, {16}));
      BodyDiff d = diff_in_body(gl, ref);
      psnr[i] = d.psnr;
      std::cout << mode_name(c.mode) << " " << label_shading_name(c.shading) << " at "
                << p.slices_per_voxel << " slices/voxel: PSNR " << d.psnr << " dB, max diff "
                << d.max_diff << ", " << d.over_8 << " of " << d.body << " pixels over 8\n";
      EXPECT_GT(d.body, 96 * 96 / 20);
      if (i == 0) {
        EXPECT_GE(d.psnr, 35.0);
        EXPECT_LE(d.max_diff, c.mode == Mode::kIso ? 96 : 32);
      } else {
        EXPECT_GE(d.psnr, 40.0);
        EXPECT_LE(d.max_diff, c.mode == Mode::kIso ? 96 : 16);
        EXPECT_LE(d.over_8, c.mode == Mode::kIso ? d.body / 10 : d.body / 100);
      }
    }
    if (c.mode != Mode::kIso) {
      EXPECT_GT(psnr[1], psnr[0] + 2.0) << mode_name(c.mode);
    }
  }
}

namespace {
Image8 read_png(const std::string& path) {
  auto in = OIIO::ImageInput::open(path);
  if (!in) {
    ADD_FAILURE() << path << ": cannot read";
    return {};
  }
  const OIIO::ImageSpec& spec = in->spec();
  Image8 out(spec.width, spec.height);
  std::vector<std::uint8_t> px(std::size_t(spec.width) * spec.height * spec.nchannels);
  in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::UINT8, px.data());
  for (std::size_t i = 0; i < std::size_t(spec.width) * spec.height; ++i)
    for (int c = 0; c < 4; ++c)
      out.rgba[4 * i + std::size_t(c)] =
          c < spec.nchannels ? px[i * std::size_t(spec.nchannels) + std::size_t(c)] : 255;
  return out;
}
}  // namespace

TEST_F(Bricks, ScriptedWindowMatchesTheHeadlessScreenshots) {
  // The interactive window under Xvfb, driven by a --script file: its frames once the view is
  // complete equal the headless --screenshot of the same view (same plan, same renderer).
  const std::string bin = std::string(VISPACK_BIN_DIR) + "/vispack-view";
  const std::string script = (dir_ / "view.script").string();
  {
    std::ofstream out(script);
    out << "# two views\nazimuth 30\nelevation 20\nscreenshot " << (dir_ / "w1.png").string()
        << "\nmode iso\nazimuth 90\nwait\nscreenshot " << (dir_ / "w2.png").string() << "\n";
  }
  const std::string common = " " + path_ + " --size 96x80 --iso -200 --opacity 0.6";
  // xvfb-run's own failures (its Xvfb not starting, or its clean-up, under a parallel ctest) are
  // retried: they say "xvfb-run: error:" and are not the viewer's.
  std::string cmd = "xvfb-run -a " + bin + common + " --script " + script;
  std::string out;
  int rc = 0;
  for (int attempt = 0; attempt < 3; ++attempt) {
    rc = vispack::test::run_command(cmd, &out);
    if (out.find("xvfb-run: error:") == std::string::npos) break;
  }
  ASSERT_EQ(rc, 0) << cmd << "\n" << out;
  const char* views[2][3] = {{"colour", "30", "w1.png"}, {"iso", "90", "w2.png"}};
  // The window's screenshot is the part the panel leaves free (the strip right of it, when the
  // viewer has the ImGui panel); the headless frame of the same view has that size.
  const viewer::PixelRect free_area = viewer::free_area(96, 80, viewer::initial_panel(96, 80));
  for (auto& v : views) {
    Image8 w = read_png((dir_ / v[2]).string());
    ASSERT_TRUE(w.width == 96 || w.width == free_area.width) << w.width;
    ASSERT_EQ(w.height, 80);
    std::string head = (dir_ / (std::string("h_") + v[2])).string();
    cmd = bin + " " + path_ + " --size " + std::to_string(w.width) +
          "x80 --iso -200 --opacity 0.6" + " --mode " + v[0] + " --azimuth " + v[1] +
          " --elevation 20" + " --screenshot " + head + " > /dev/null 2>&1";
    ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
    Image8 h = read_png(head);
    BodyDiff d = diff_in_body(w, h);
    std::cout << "window vs headless, " << v[0] << ": PSNR " << d.psnr << " dB, max diff "
              << d.max_diff << ", body " << d.body << "\n";
    EXPECT_GT(d.body, w.width * 80 / 20) << v[0];
    EXPECT_GE(d.psnr, 50.0) << v[0];
    EXPECT_LE(d.max_diff, 2) << v[0];
  }
  // A bad script is refused with a usage error naming the line, before any window opens (so
  // without xvfb-run, whose own clean-up can fail under a parallel ctest and exit 5).
  std::ofstream(script) << "azimuth 30\nfly away\n";
  rc = vispack::test::run_command(bin + common + " --script " + script, &out);
  EXPECT_EQ(rc, 2) << out;
  EXPECT_NE(out.find("view.script:2: unknown command 'fly'"), std::string::npos) << out;
}

int main(int argc, char** argv) {
  g_argv.assign(argv, argv + argc);
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}

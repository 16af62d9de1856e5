// config_to_json / write_config: what load_config reads back is what was written, paths are
// written relative to the config's folder, and the written file is valid for the loader.
#include <gtest/gtest.h>

#include <filesystem>

#include <nlohmann/json.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/core/config.h"

namespace vp = vispack::pipeline;
namespace vph = vispack::phantom;
using nlohmann::json;
using vispack::test::TempDir;

namespace {

void expect_same(const vp::Config& a, const vp::Config& b) {
  EXPECT_EQ(a.name, b.name);
  EXPECT_EQ(a.work_dir, b.work_dir);
  EXPECT_EQ(a.output, b.output);
  EXPECT_EQ(a.vdb_output, b.vdb_output);
  EXPECT_EQ(a.spacing_mm, b.spacing_mm);
  EXPECT_EQ(a.rgb.dir, b.rgb.dir);
  EXPECT_EQ(a.rgb.pattern, b.rgb.pattern);
  ASSERT_EQ(a.rgb.raw.has_value(), b.rgb.raw.has_value());
  if (a.rgb.raw) {
    EXPECT_EQ(a.rgb.raw->width, b.rgb.raw->width);
    EXPECT_EQ(a.rgb.raw->planar, b.rgb.raw->planar);
    EXPECT_EQ(a.rgb.raw->channels, b.rgb.raw->channels);
  }
  ASSERT_EQ(a.ct.has_value(), b.ct.has_value());
  if (a.ct) {
    EXPECT_EQ(a.ct->dir, b.ct->dir);
    EXPECT_EQ(a.ct->pixel_spacing_mm, b.ct->pixel_spacing_mm);
    EXPECT_EQ(a.ct->slope, b.ct->slope);
    EXPECT_EQ(a.ct->intercept, b.ct->intercept);
    EXPECT_EQ(a.ct->slice_spacing_mm, b.ct->slice_spacing_mm);
    EXPECT_EQ(a.ct->z_offset_mm, b.ct->z_offset_mm);
  }
  ASSERT_EQ(a.seg.has_value(), b.seg.has_value());
  if (a.seg) {
    EXPECT_EQ(a.seg->palette, b.seg->palette);
    EXPECT_EQ(a.seg->tolerance, b.seg->tolerance);
    EXPECT_EQ(a.seg->mode, b.seg->mode);
    EXPECT_EQ(a.seg->slice_spacing_mm, b.seg->slice_spacing_mm);
    EXPECT_EQ(a.seg->z_offset_mm, b.seg->z_offset_mm);
  }
  const auto &ra = a.registration, &rb = b.registration;
  EXPECT_EQ(ra.method, rb.method);
  EXPECT_EQ(ra.jump_px, rb.jump_px);
  EXPECT_EQ(ra.overrides, rb.overrides);
  EXPECT_EQ(ra.output_frame.rotation_deg, rb.output_frame.rotation_deg);
  EXPECT_EQ(ra.output_frame.dx_px, rb.output_frame.dx_px);
  EXPECT_EQ(ra.output_frame.dy_px, rb.output_frame.dy_px);
  EXPECT_EQ(ra.anchor, rb.anchor);
  EXPECT_EQ(a.mask.hu_threshold, b.mask.hu_threshold);
  EXPECT_EQ(a.mask.gel_colour, b.mask.gel_colour);
  EXPECT_EQ(a.pack.brick_edge, b.pack.brick_edge);
  EXPECT_EQ(a.pack.keep_colour_outside_body, b.pack.keep_colour_outside_body);
  EXPECT_EQ(a.pack.keep_ct_outside_body, b.pack.keep_ct_outside_body);
  EXPECT_EQ(a.pack.crop_margin_px, b.pack.crop_margin_px);
  EXPECT_EQ(a.work.write_registered, b.work.write_registered);
  EXPECT_EQ(a.work.write_ct, b.work.write_ct);
  EXPECT_EQ(a.work.overlay_max_px, b.work.overlay_max_px);
  EXPECT_EQ(a.vdb.enabled, b.vdb.enabled);
  EXPECT_EQ(a.vdb.level, b.vdb.level);
  EXPECT_EQ(a.vdb.layout, b.vdb.layout);
  EXPECT_EQ(a.vdb.max_memory_mb, b.vdb.max_memory_mb);
}

}  // namespace

TEST(ConfigWriter, RoundTripsThroughTheLoader) {
  TempDir dir("vispack-config-writer");
  vph::PhantomOptions po;
  po.preset = "tiny";
  po.slices = 3;
  po.rgb_raw = true;
  po.quiet = true;
  vph::make_phantom(dir.path(), po);
  vp::Config a = vp::load_config(dir / "config.json");
  // Non-default values everywhere the phantom leaves defaults.
  a.registration.output_frame = {1.25, -3.5, 7.0};
  a.registration.anchor = "ct";
  a.mask.gel_colour = std::array<int, 3>{30, 60, 200};
  a.pack.brick_edge = 32;
  a.pack.keep_colour_outside_body = true;
  a.pack.crop_margin_px = 12;
  a.work.write_ct = true;
  a.work.overlay_max_px = 0;
  a.ct->slice_spacing_mm = 3.0;
  a.ct->z_offset_mm = -2.5;
  a.seg->slice_spacing_mm = 2.0;
  a.seg->z_offset_mm = 1.0;
  a.vdb.level = 1;
  a.vdb.layout = vp::VdbLayout::kFile;
  a.vdb.max_memory_mb = 300;
  vp::write_config(dir / "again.json", a);
  const vp::Config b = vp::load_config(dir / "again.json");
  expect_same(a, b);
  // Paths are relative to the config's folder (the folder can move).
  const json j = json::parse(vispack::read_file(dir / "again.json"));
  EXPECT_EQ(j["rgb"]["dir"], "rgb");
  EXPECT_EQ(j["seg"]["palette"], "palette.json");
  EXPECT_EQ(j["work_dir"], "work");
  EXPECT_EQ(j["register"]["output_frame"]["dx_px"], -3.5);
  // Written from a sub-folder: paths go up.
  std::filesystem::create_directories(dir / "sub");
  vp::write_config(dir / "sub/c.json", a);
  const json k = json::parse(vispack::read_file(dir / "sub/c.json"));
  EXPECT_EQ(k["rgb"]["dir"], "../rgb");
  expect_same(a, vp::load_config(dir / "sub/c.json"));
}

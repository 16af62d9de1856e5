// viewer_bench [--file X.vpk] [--size N] [--dims X,Y,Z]: speed against error of the slice
// renderer, time to first frame and upload throughput, on whatever GL the headless context
// gets (llvmpipe here). Without --file it writes a medium-sized synthetic volume (the size of
// the `medium` phantom, 512x384x160, bricks of 64) to a temporary file first.
// Prints a Markdown table for docs/BENCHMARKS.md.
// --json OUT also writes every row plus the camera (world mm) and the level-0 box, so that a peer
// renderer (scripts/bench/vtk_peer.py) can render the same view; --spv LIST sets the slices per
// voxel (default 0.5,1,2,4); with --json, colour frames of the coarser levels (levels of detail,
// 1 slice per voxel) are timed against the same level-0 reference; --ref-png OUT saves it.
// The brick-paged renderer (issue 14) is measured first: time to the first picture, then per
// mode the bricks drawn (levels), skipped and culled, the bytes uploaded against the whole level,
// the load time and the frame time at the level the screen footprint asks for; --psnr adds its
// foreground PSNR against the CPU reference of the finest level it draws. --paged-only skips
// the whole-level measurements (which upload level 0 whole).
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "../render/synthetic_volume.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/cli.h"
#include "vispack/format/writer.h"
#include "vispack/render/brick_tree.h"
#include "vispack/render/lost_slices.h"
#include "vispack/render/reference.h"
#include "vispack/viewer/brick_cache.h"
#include "vispack/viewer/context.h"
#include "vispack/viewer/slice_renderer.h"

using namespace vispack;
using namespace vispack::render;

namespace {
double now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// CPU seconds of the process (all llvmpipe threads): load-independent frame cost.
double cpu_seconds() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

// Foreground PSNR (pixels where either image is not black) and max difference.
std::pair<double, int> body_psnr(const Image8& a, const Image8& b) {
  double se = 0;
  std::int64_t n = 0;
  int worst = 0;
  for (std::size_t i = 0; i + 3 < a.rgba.size(); i += 4) {
    bool lit = false;
    for (int c = 0; c < 3; ++c)
      lit = lit || a.rgba[i + c] || b.rgba[i + c];
    if (!lit) continue;
    ++n;
    for (int c = 0; c < 3; ++c) {
      int e = std::abs(int(a.rgba[i + c]) - int(b.rgba[i + c]));
      se += double(e) * e;
      worst = std::max(worst, e);
    }
  }
  return {se == 0 ? 99.0 : 10 * std::log10(255.0 * 255.0 * 3.0 * double(n) / se), worst};
}

void paged_bench(const std::string& path, int size, std::int64_t gpu_mb, bool psnr,
                 nlohmann::json& out) {
  double t_open = now();
  std::shared_ptr<const VolumeSource> source = fill_lost_slices(open_packed(path));
  viewer::HeadlessContext context;
  viewer::SliceRenderer renderer;
  BrickTree tree(*source);
  auto cache = std::make_unique<viewer::BrickCache>(*source, gpu_mb << 20, 0);
  LevelGeometry g0 = source->level(0);
  OrbitParams orbit;
  orbit.target = g0.box().centre();
  orbit.azimuth_deg = 30;
  orbit.elevation_deg = 20;
  Camera cam = orbit_camera(orbit, g0.box(), size, size);
  RenderParams base;
  base.opacity = 0.6;
  base.label_colours = make_label_colours(source->labels(), 0.5);
  base.reference_length_mm = reference_length(g0);
  const int levels = source->level_count();
  {
    PlanOptions first;
    first.finest_level = first.coarsest_level = levels - 1;
    unsigned ch = channels_for(base, tree.present_channels());
    BrickPlan plan = plan_bricks(tree, cam, base, first, ch);
    cache->request(plan.draw, ch);
    cache->pump(-1);
    cache->use(plan.draw);
    renderer.render_bricks(*cache, tree, plan, cam, base);
    renderer.read_rgba8();
  }
  const double first_picture = now() - t_open;
  std::printf(
      "\n%s\n\nbrick-paged renderer, %dx%d frame, volume %lldx%lldx%lld, bricks of %d, "
      "%d levels\n\n| what | value |\n|---|---|\n| first picture after open (coarsest "
      "level) | %.3f s |\n",
      context.description().c_str(), size, size, (long long)g0.dims[0], (long long)g0.dims[1],
      (long long)g0.dims[2], source->brick_edge(), levels, first_picture);
  out["paged_first_picture_s"] = first_picture;
  std::printf(
      "\n| mode | slices/voxel | bricks drawn (per level) | skipped empty bricks | "
      "skipped empty cells | culled | uploaded MB | whole level MB | load s | frame ms | "
      "frame CPU s |%s\n|---|---|---|---|---|---|---|---|---|---|---|%s\n",
      psnr ? " PSNR (dB) / max diff |" : "", psnr ? "---|" : "");
  nlohmann::json rows = nlohmann::json::array();
  for (double spv : {2.0, 1.0})
    for (Mode m : {Mode::kColour, Mode::kCt, Mode::kIso, Mode::kLabels, Mode::kMip, Mode::kTf2d}) {
      RenderParams p = base;
      p.mode = m;
      p.slices_per_voxel = spv;
      if (m == Mode::kCt) p.opacity = 0.3;
      if (m == Mode::kIso) p.iso_hu = 300;
      const unsigned ch = channels_for(p, tree.present_channels());
      PlanOptions popt;
      popt.max_bytes = gpu_mb << 20;
      popt.border = viewer::BrickCache::kBorder;
      BrickPlan plan = plan_bricks(tree, cam, p, popt, ch);
      // A fresh cache per mode at the first density: its uploads are that frame's own.
      if (spv == 2.0) cache = std::make_unique<viewer::BrickCache>(*source, gpu_mb << 20, 0);
      cache->reset_counters();
      double t0 = now();
      cache->request(plan.draw, ch);
      cache->pump(-1);
      cache->use(plan.draw);
      const double load_s = now() - t0;
      const std::int64_t uploaded = cache->stats().uploaded_bytes;
      renderer.render_bricks(*cache, tree, plan, cam, p);  // warm-up (shader compile)
      renderer.read_rgba8();
      const int reps = 2;
      t0 = now();
      const double cpu0 = cpu_seconds();
      Image8 img;
      viewer::FrameInfo info;
      for (int r = 0; r < reps; ++r) {
        info = renderer.render_bricks(*cache, tree, plan, cam, p);
        img = renderer.read_rgba8();
      }
      const double ms = (now() - t0) / reps * 1e3;
      const double cpu = (cpu_seconds() - cpu0) / reps;
      int per_level[64] = {0}, finest = levels - 1;
      for (const BrickKey& k : plan.draw) {
        per_level[k.level]++;
        finest = std::min(finest, k.level);
      }
      std::string mix;
      for (int l = 0; l < levels; ++l)
        if (per_level[l])
          mix +=
              (mix.empty() ? "" : ", ") + std::to_string(per_level[l]) + " L" + std::to_string(l);
      std::int64_t whole = 0;
      for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
        if (ch & channel_bit(c)) whole += source->level(finest).voxels() * channel_bytes(c);
      std::string psnr_cell;
      nlohmann::json row = {{"mode", mode_name(m)},
                            {"drawn", plan.draw.size()},
                            {"slices_per_voxel", spv},
                            {"cells_skipped", info.cells_skipped},
                            {"frame_cpu_s", cpu},
                            {"levels", mix},
                            {"skipped", plan.skipped},
                            {"culled", plan.culled},
                            {"uploaded_mb", uploaded / 1e6},
                            {"whole_level", finest},
                            {"whole_level_mb", whole / 1e6},
                            {"load_s", load_s},
                            {"frame_ms", ms}};
      if (psnr) {
        VolumeData level = load_level(*source, finest);
        Image8 ref = to_rgba8(render_reference(level, cam, p, {4}));
        auto [db, worst] = body_psnr(img, ref);
        psnr_cell = " " + std::to_string(db).substr(0, 5) + " / " + std::to_string(worst) + " |";
        row["psnr_db"] = db;
        row["max_diff"] = worst;
      }
      std::printf(
          "| %s | %.0f | %zu (%s) | %lld | %lld | %lld | %.1f | %.1f (L%d) | %.2f | %.0f | "
          "%.2f |%s\n",
          mode_name(m), spv, plan.draw.size(), mix.c_str(), (long long)plan.skipped,
          (long long)info.cells_skipped, (long long)plan.culled, uploaded / 1e6, whole / 1e6,
          finest, load_s, ms, cpu, psnr_cell.c_str());
      rows.push_back(row);
    }
  out["paged"] = rows;
}

}  // namespace

int main(int argc, char** argv) {
  return run_main("viewer_bench", argc, argv, [](Args& args) {
    args.describe("[--file X.vpk] [--size N] [--dims X,Y,Z]", "Slice renderer benchmark.");
    auto file = args.option("--file", "X.vpk", "packed volume (default: synthetic medium)");
    auto size_opt = args.option_int("--size", "N", "frame size (default 256)");
    std::string dims_text = args.option("--dims", "X,Y,Z", "synthetic dims", "512,384,160");
    auto json_out = args.option("--json", "OUT", "also write the results as JSON");
    std::string spv_text =
        args.option("--spv", "LIST", "slices per voxel, comma separated", "0.5,1,2,4");
    auto ref_png = args.option("--ref-png", "OUT", "save the colour CPU reference frame");
    bool paged_only = args.flag("--paged-only", "skip the whole-level measurements");
    bool paged_psnr = args.flag("--psnr", "paged frames: PSNR against the reference");
    auto gpu_mb = args.option_int("--max-gpu-mb", "MB", "brick cache budget (default 2048)");
    args.done();
    std::vector<double> spv;
    for (std::size_t pos = 0; pos < spv_text.size();) {
      std::size_t end = spv_text.find(',', pos);
      if (end == std::string::npos) end = spv_text.size();
      const double v = std::atof(spv_text.substr(pos, end - pos).c_str());
      if (!(v > 0)) throw UsageError("--spv must list positive numbers");
      spv.push_back(v);
      pos = end + 1;
    }
    nlohmann::json out;
    std::setvbuf(stdout, nullptr, _IOLBF, 0);  // lines appear as they are measured
    int size = int(size_opt.value_or(256));
    std::string path;
    std::filesystem::path tmp;
    if (file) {
      path = *file;
    } else {
      int d[3];
      if (std::sscanf(dims_text.c_str(), "%d,%d,%d", &d[0], &d[1], &d[2]) != 3)
        throw UsageError("--dims must be X,Y,Z");
      tmp = std::filesystem::temp_directory_path() / ("viewer_bench_" + std::to_string(getpid()));
      std::filesystem::create_directories(tmp);
      path = (tmp / "medium.vpk").string();
      double t0 = now();
      auto v = synthetic::make_synthetic(d[0], d[1], d[2], {0.33, 0.33, 1.0});
      format::WriterOptions o;
      o.dims = v->geometry.dims;
      o.spacing_mm = {0.33, 0.33, 1.0};
      o.brick_edge = 64;
      o.channels = {{"rgba", format::ChannelType::kRgba8},
                    {"ct", format::ChannelType::kInt16},
                    {"labels", format::ChannelType::kUint16}};
      for (const Label& l : v->label_table)
        o.label_table.push_back({l.id, l.name, l.colour});
      format::write_volume(path, o, {v->rgba.data(), v->ct.data(), v->labels.data()});
      std::printf("synthetic %dx%dx%d written in %.1f s\n", d[0], d[1], d[2], now() - t0);
    }

    paged_bench(path, size, gpu_mb.value_or(2048), paged_psnr, out);
    if (paged_only) {
      if (json_out) write_file_atomic(*json_out, out.dump(1));
      if (!tmp.empty()) std::filesystem::remove_all(tmp);
      return 0;
    }

    // Time to first frame: open, context, coarsest level, one frame read back.
    double t_open = now();
    auto source = open_packed(path);
    viewer::HeadlessContext context;
    viewer::SliceRenderer renderer;
    viewer::VolumeTextures coarse;
    int coarsest = source->level_count() - 1;
    coarse.upload(*source, coarsest, 0);
    LevelGeometry g0 = source->level(0);
    OrbitParams orbit;
    orbit.target = g0.box().centre();
    orbit.azimuth_deg = 30;
    orbit.elevation_deg = 20;
    Camera cam = orbit_camera(orbit, g0.box(), size, size);
    RenderParams params;
    params.opacity = 0.6;
    params.label_colours = make_label_colours(source->labels(), 0.5);
    renderer.render(coarse, cam, params);
    renderer.read_rgba8();
    double first_frame = now() - t_open;

    viewer::VolumeTextures fine;
    viewer::UploadStats up = fine.upload(*source, 0, 0);
    std::printf("\n%s\n\n", context.description().c_str());
    std::printf("| what | value |\n|---|---|\n");
    std::printf("| volume | %lldx%lldx%lld, %d levels |\n", (long long)g0.dims[0],
                (long long)g0.dims[1], (long long)g0.dims[2], source->level_count());
    std::printf("| time to first frame (open + level %d + %dx%d frame) | %.3f s |\n", coarsest,
                size, size, first_frame);
    std::printf("| upload level 0 (%lld bricks, %.0f MB) | %.2f s, %.0f MB/s |\n",
                (long long)up.bricks, up.bytes / 1e6, up.seconds, up.bytes / 1e6 / up.seconds);
    auto vec = [](const Vec3& v) { return nlohmann::json{v.x, v.y, v.z}; };
    out["gl"] = context.description();
    out["dims"] = g0.dims;
    out["spacing_mm"] = vec(g0.spacing_mm);
    out["box_lo"] = vec(g0.box().lo);
    out["box_hi"] = vec(g0.box().hi);
    out["levels"] = source->level_count();
    out["size"] = size;
    out["first_frame_s"] = first_frame;
    out["upload_s"] = up.seconds;
    out["upload_mb"] = up.bytes / 1e6;
    out["camera"] = {
        {"eye", vec(cam.eye)},        {"forward", vec(cam.forward)},      {"up", vec(cam.up)},
        {"fov_y_deg", cam.fov_y_deg}, {"orthographic", cam.orthographic}, {"near_mm", cam.near_mm},
        {"far_mm", cam.far_mm}};
    out["opacity"] = params.opacity;
    nlohmann::json rows = nlohmann::json::array();

    VolumeData data = load_level(*source, 0);
    std::printf(
        "\n| mode | slices/voxel | slices | frame time (ms, %dx%d) | PSNR vs reference (dB) |\n"
        "|---|---|---|---|---|\n",
        size, size);
    for (Mode m : {Mode::kColour, Mode::kLabels}) {
      RenderParams p = params;
      p.mode = m;
      if (m == Mode::kCt) p.opacity = 0.3;
      double t_ref = now();
      Image8 ref = to_rgba8(render_reference(data, cam, p, {8}));
      t_ref = now() - t_ref;
      if (ref_png && m == Mode::kColour) write_png(*ref_png, ref);
      for (double s : spv) {
        p.slices_per_voxel = s;
        viewer::FrameInfo info = renderer.render(fine, cam, p);  // warm-up
        renderer.read_rgba8();
        const int reps = 2;
        double t0 = now();
        Image8 img;
        for (int r = 0; r < reps; ++r) {
          renderer.render(fine, cam, p);
          img = renderer.read_rgba8();
        }
        double ms = (now() - t0) / reps * 1e3;
        const double psnr = psnr_rgb(img, ref);
        std::printf("| %s | %.1f | %lld | %.0f | %.1f |\n", mode_name(m), s, (long long)info.slices,
                    ms, psnr);
        rows.push_back({{"mode", mode_name(m)},
                        {"level", 0},
                        {"slices_per_voxel", s},
                        {"slices", info.slices},
                        {"ms", ms},
                        {"psnr_db", psnr}});
      }
      // Levels of detail: the coarser levels' textures, 1 slice per voxel of that level.
      for (int level = 1; json_out && m == Mode::kColour && level < source->level_count();
           ++level) {
        viewer::VolumeTextures lod;
        lod.upload(*source, level, 0);
        p.slices_per_voxel = 1.0;
        viewer::FrameInfo info = renderer.render(lod, cam, p);  // warm-up
        renderer.read_rgba8();
        const int reps = 2;
        double t0 = now();
        Image8 img;
        for (int r = 0; r < reps; ++r) {
          renderer.render(lod, cam, p);
          img = renderer.read_rgba8();
        }
        const double ms = (now() - t0) / reps * 1e3;
        const double psnr = psnr_rgb(img, ref);
        std::printf("| %s, level %d | 1.0 | %lld | %.0f | %.1f |\n", mode_name(m), level,
                    (long long)info.slices, ms, psnr);
        rows.push_back({{"mode", mode_name(m)},
                        {"level", level},
                        {"slices_per_voxel", 1.0},
                        {"slices", info.slices},
                        {"ms", ms},
                        {"psnr_db", psnr}});
      }
      std::fprintf(stderr, "(reference %s: %.1f s)\n", mode_name(m), t_ref);
    }
    out["rows"] = rows;
    if (json_out) write_file_atomic(*json_out, out.dump(1));
    if (!tmp.empty()) std::filesystem::remove_all(tmp);
    return 0;
  });
}

// viewer_bench [--file X.vpk] [--size N] [--dims X,Y,Z]: speed against error of the slice
// renderer, time to first frame and upload throughput, on whatever GL the headless context
// gets (llvmpipe here). Without --file it writes a medium-sized synthetic volume (the size of
// the `medium` phantom, 512x384x160, bricks of 64) to a temporary file first (--keep OUT: to OUT,
// kept, so that later runs can read it with --file).
// Prints a Markdown table for docs/BENCHMARKS.md.
// --json OUT also writes every row plus the camera (world mm) and the level-0 box, so that a peer
// renderer (scripts/bench/vtk_peer.py) can render the same view; --spv LIST sets the slices per
// voxel (default 0.5,1,2,4); with --json, colour frames of the coarser levels (levels of detail,
// 1 slice per voxel) are timed against the same level-0 reference; --ref-png OUT saves it.
// The brick-paged renderer (docs/BENCHMARKS.md, 'Viewer: bricks paged by view') is measured first:
// time to the first picture, then per mode the bricks drawn (levels), skipped and culled, the bytes
// uploaded against the whole level, the load time and the frame time at the level the screen
// footprint asks for; --psnr adds its foreground PSNR against the CPU reference of the finest level
// it draws. --paged-only skips the whole-level measurements (which upload level 0 whole),
// --no-paged the paged ones;
// --modes LIST restricts the paged modes, --reps N sets the frames timed per row (median);
// --level L draws level L only in the paged frames (finest = coarsest = L: level 0 at any frame
// size; raise --max-gpu-mb to hold it), instead of the level the screen footprint asks for.
// Long files (docs/BENCHMARKS.md, 'Viewer on long files'): --stack X,Y,Z --keep OUT.vpk writes a
// synthetic stack slice by slice through the streaming writer (a body whose section changes
// along z, colour, CT and labels, zeros outside it as the pipeline stores them, 4 runs of 3 lost
// slices; memory: one brick row); --orbit then measures, as vispack-view opens a file: the first
// picture (coarsest level; --eager-tree builds every level's brick tree first, as before), the
// brick tree of every level, a colour frame after load, and an orbit of 36 frames (10 degrees
// apart, each loaded in full) with the brick cache's resident bytes and the process's resident
// set sampled every frame against the cache's budget (--max-gpu-mb).
// Quality is the foreground PSNR (render::diff_foreground: pixels where either image is not
// black) against vispack's CPU reference ray caster at 8 steps per voxel of the same transfer
// function; the whole-frame PSNR is kept beside it for the record. scripts/bench/viewer_peers.py
// runs this and VTK's ray caster (scripts/bench/vtk_peer.py) alternately, process by process.
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "../render/synthetic_volume.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/cli.h"
#include "vispack/common/error.h"
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

// Median of the wall times of `reps` frames (render + read-back); `img` gets the last frame.
template <class Frame>
double median_ms(int reps, Frame&& frame) {
  std::vector<double> ms;
  for (int r = 0; r < reps; ++r) {
    const double t0 = now();
    frame();
    ms.push_back((now() - t0) * 1e3);
  }
  std::sort(ms.begin(), ms.end());
  return ms.size() % 2 ? ms[ms.size() / 2] : 0.5 * (ms[ms.size() / 2 - 1] + ms[ms.size() / 2]);
}

// One row of the whole-level table: printed, and returned for the JSON. `psnr_db` is the
// foreground PSNR (the quality measure), `psnr_whole_frame_db` the old whole-frame one.
nlohmann::json quality_row(const char* mode, int level, double spv, std::int64_t slices, double ms,
                           const Image8& img, const Image8& ref) {
  const ForegroundDiff d = diff_foreground(img, ref);
  const double whole = psnr_rgb(img, ref);
  const std::string what = level ? std::string(mode) + ", level " + std::to_string(level) : mode;
  std::printf("| %s | %.2g | %lld | %.1f | %.2f | %d | %.1f |\n", what.c_str(), spv,
              (long long)slices, ms, d.psnr_db, d.max_diff, whole);
  return {{"mode", mode},
          {"level", level},
          {"slices_per_voxel", spv},
          {"slices", slices},
          {"ms", ms},
          {"psnr_db", d.psnr_db},
          {"max_diff", d.max_diff},
          {"foreground_pixels", d.pixels},
          {"psnr_whole_frame_db", whole}};
}

// Resident set of this process (VmRSS), bytes; 0 when /proc is unreadable.
std::int64_t resident_set_bytes() {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::int64_t(std::atoll(line.c_str() + 6)) * 1024;
  return 0;
}

// The synthetic stack of --stack, slice by slice: a body of elliptic section whose radii and
// centre drift along z, smooth colour with 3 bits of noise (so that bricks compress like tissue,
// not like a constant), CT soft tissue with two bone rods, labels skin (1), tissue (2), bone (3);
// colour 0, CT -1024 HU and label 0 outside (what the pipeline stores outside the body mask).
// Slices listed in `black` are black in colour (lost slices; listed in the metadata).
void write_stack(const std::string& path, std::int64_t nx, std::int64_t ny, std::int64_t nz,
                 const std::vector<std::int64_t>& black) {
  format::WriterOptions o;
  o.dims = {nx, ny, nz};
  o.spacing_mm = {0.33, 0.33, 1.0};
  o.brick_edge = 64;
  o.threads = 2;
  o.channels = {{"rgba", format::ChannelType::kRgba8},
                {"ct", format::ChannelType::kInt16},
                {"labels", format::ChannelType::kUint16}};
  o.label_table = {
      {1, "skin", {230, 180, 150}}, {2, "tissue", {200, 60, 60}}, {3, "bone", {240, 240, 220}}};
  o.extra_metadata = {{"slices", {{"black", black}}}};
  format::Writer writer(path, o);
  const std::size_t plane = std::size_t(nx * ny);
  std::vector<std::uint8_t> rgba(4 * plane);
  std::vector<std::int16_t> ct(plane);
  std::vector<std::uint16_t> labels(plane);
  for (std::int64_t z = 0; z < nz; ++z) {
    const double t = double(z) / double(std::max<std::int64_t>(nz - 1, 1));
    const double rx = nx * (0.30 + 0.08 * std::sin(6.0 * t)),
                 ry = ny * (0.33 + 0.05 * std::cos(4.0 * t));
    const double cx = 0.5 * nx + 0.02 * nx * std::sin(3.0 * t), cy = 0.5 * ny;
    const bool lost = std::binary_search(black.begin(), black.end(), z);
    for (std::int64_t y = 0; y < ny; ++y)
      for (std::int64_t x = 0; x < nx; ++x) {
        const std::size_t i = std::size_t(x + nx * y);
        const double ex = (double(x) - cx) / rx, ey = (double(y) - cy) / ry;
        const double depth = (1.0 - std::sqrt(ex * ex + ey * ey)) * std::min(rx, ry);  // voxels
        if (depth <= 0) {
          std::memset(&rgba[4 * i], 0, 4);
          ct[i] = -1024;
          labels[i] = 0;
          continue;
        }
        const double bx = std::fabs(double(x) - cx) - 0.35 * rx, by = double(y) - cy;
        const bool bone = bx * bx + by * by < 0.01 * rx * rx;
        std::uint64_t h = std::uint64_t(x + nx * (y + ny * z)) * 0x9E3779B97F4A7C15ull;
        const int pattern = int((h ^ (h >> 29)) >> 61);  // 0..7, texture noise
        if (lost) {
          std::memset(&rgba[4 * i], 0, 4);
        } else {
          rgba[4 * i + 0] = std::uint8_t(std::min(255.0, 120 + 100 * ex * ex + pattern));
          rgba[4 * i + 1] = std::uint8_t(std::min(255.0, 70 + 60 * std::fabs(ey) + pattern));
          rgba[4 * i + 2] = std::uint8_t(60 + 40 * t);
          rgba[4 * i + 3] = std::uint8_t(std::min(255.0, 128.0 * depth));
        }
        ct[i] = std::int16_t(bone ? 700 + 3 * pattern : 20 + 2 * pattern);
        labels[i] = depth < 6 ? 1 : (bone ? 3 : 2);
      }
    writer.append_slice({rgba.data(), ct.data(), labels.data()});
  }
  writer.finish();
}

// The 4 runs of 3 lost slices of a stack of nz (at a fifth, two, three and four fifths).
std::vector<std::int64_t> black_slices(std::int64_t nz) {
  std::vector<std::int64_t> out;
  for (int k = 1; k <= 4 && nz >= 15; ++k)
    for (int j = 0; j < 3; ++j)
      out.push_back(k * nz / 5 + j);
  return out;
}

// What a user sees opening `path`: the first picture, the brick tree, a size² colour frame after
// load and an orbit of 36 frames with the cache's memory against its budget.
void orbit_bench(const std::string& path, int size, std::int64_t gpu_mb, bool eager, int reps,
                 nlohmann::json& out) {
  const double t_open = now(), cpu_open = cpu_seconds();
  std::shared_ptr<const VolumeSource> source = fill_lost_slices(open_packed(path));
  const double t_file = now() - t_open;
  viewer::HeadlessContext context;
  viewer::SliceRenderer renderer;
  const double t_tree0 = now();
  BrickTree tree(*source, eager ? TreeBuild::kEager : TreeBuild::kCoarseFirst);
  const double tree_first_s = now() - t_tree0;
  const std::int64_t level0_stats_first = tree.stats_reads(0);
  viewer::BrickCache cache(*source, gpu_mb << 20, 0);
  const LevelGeometry g0 = source->level(0);
  const int levels = source->level_count();
  OrbitParams orbit;
  orbit.target = g0.box().centre();
  orbit.azimuth_deg = 30;
  orbit.elevation_deg = 20;
  RenderParams p;  // vispack-view's colour defaults (its mode defaults are the app's)
  p.opacity = 0.6;
  p.label_colours = make_label_colours(source->labels(), 0.5);
  p.reference_length_mm = reference_length(g0);
  const unsigned ch = channels_for(p, tree.present_channels());
  Camera cam = orbit_camera(orbit, g0.box(), size, size);
  {
    PlanOptions first;
    first.finest_level = first.coarsest_level = levels - 1;
    BrickPlan plan = plan_bricks(tree, cam, p, first, ch);
    cache.request(plan.draw, ch);
    cache.pump(-1);
    cache.use(plan.draw);
    renderer.render_bricks(cache, tree, plan, cam, p);
    renderer.read_rgba8();
  }
  const double first_picture = now() - t_open, first_picture_cpu = cpu_seconds() - cpu_open;
  const double t_all0 = now(), cpu_all0 = cpu_seconds();
  tree.build_all();
  const double tree_rest_s = now() - t_all0, tree_rest_cpu = cpu_seconds() - cpu_all0;
  PlanOptions popt;
  popt.max_bytes = gpu_mb << 20;
  popt.border = viewer::BrickCache::kBorder;
  // A frame after load: every brick of the plan resident, then timed (median of reps).
  BrickPlan plan = plan_bricks(tree, cam, p, popt, ch);
  double t0 = now();
  cache.request(plan.draw, ch);
  cache.pump(-1);
  cache.use(plan.draw);
  const double load_s = now() - t0;
  renderer.render_bricks(cache, tree, plan, cam, p);  // warm-up (shader compile)
  renderer.read_rgba8();
  const double cpu0 = cpu_seconds();
  const double frame_ms = median_ms(reps, [&] {
    renderer.render_bricks(cache, tree, plan, cam, p);
    renderer.read_rgba8();
  });
  const double frame_cpu = (cpu_seconds() - cpu0) / reps;
  // The orbit: 36 frames 10 degrees apart, each loaded in full, then drawn and read back.
  std::vector<double> orbit_ms, orbit_load_s;
  std::int64_t max_resident = 0, max_rss = 0, evicted0 = cache.stats().evicted;
  nlohmann::json frames = nlohmann::json::array();
  const std::int64_t budget = cache.budget_bytes();
  for (int f = 0; f < 36; ++f) {
    OrbitParams o = orbit;
    o.azimuth_deg = orbit.azimuth_deg + 10.0 * f;
    const Camera c = orbit_camera(o, g0.box(), size, size);
    const BrickPlan fp = plan_bricks(tree, c, p, popt, ch);
    const double l0 = now();
    cache.request(fp.draw, ch);
    cache.pump(-1);
    cache.use(fp.draw);
    const double l1 = now();
    renderer.render_bricks(cache, tree, fp, c, p);
    renderer.read_rgba8();
    const double l2 = now();
    const std::int64_t resident = cache.stats().resident_bytes, rss = resident_set_bytes();
    max_resident = std::max(max_resident, resident);
    max_rss = std::max(max_rss, rss);
    orbit_ms.push_back((l2 - l1) * 1e3);
    orbit_load_s.push_back(l1 - l0);
    frames.push_back({{"azimuth_deg", o.azimuth_deg},
                      {"bricks", fp.draw.size()},
                      {"load_s", l1 - l0},
                      {"frame_ms", (l2 - l1) * 1e3},
                      {"resident_mb", resident / 1e6},
                      {"rss_mb", rss / 1e6}});
  }
  auto sorted = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v;
  };
  const std::vector<double> ms = sorted(orbit_ms), ls = sorted(orbit_load_s);
  int finest = levels - 1;
  for (const BrickKey& k : plan.draw)
    finest = std::min(finest, k.level);
  std::printf(
      "\n%s\n\nvolume %lldx%lldx%lld, bricks of %d, %d levels, %zu lost slices, %.2f GB; brick "
      "tree %s; %dx%d frames; cache budget %lld MB\n\n| what | value |\n|---|---|\n"
      "| open the file (index, metadata) | %.3f s |\n"
      "| brick tree before the first picture | %.3f s (%lld level-0 stats read) |\n"
      "| first picture after open (coarsest level, %dx%d) | %.3f s (%.2f CPU s) |\n"
      "| brick tree of every level, after the first picture | %.3f s (%.2f CPU s) |\n"
      "| colour frame after load: bricks (level %d..%d), load, frame | %zu, %.2f s, %.0f ms "
      "(%.2f CPU s) |\n"
      "| orbit of 36 frames: frame ms median / max | %.0f / %.0f |\n"
      "| orbit: load s median / max (bricks not resident yet) | %.2f / %.2f |\n"
      "| orbit: brick cache resident, max (budget) | %.0f MB (%lld MB): %s |\n"
      "| orbit: evicted bricks / process resident set, max | %lld / %.0f MB |\n",
      context.description().c_str(), (long long)g0.dims[0], (long long)g0.dims[1],
      (long long)g0.dims[2], source->brick_edge(), levels, source->lost_slices().size(),
      double(std::filesystem::file_size(path)) / 1e9, eager ? "eager (as before)" : "coarse first",
      size, size, (long long)gpu_mb, t_file, tree_first_s, (long long)level0_stats_first, size,
      size, first_picture, first_picture_cpu, tree_rest_s, tree_rest_cpu, finest, levels - 1,
      plan.draw.size(), load_s, frame_ms, frame_cpu, ms[ms.size() / 2], ms.back(),
      ls[ls.size() / 2], ls.back(), max_resident / 1048576.0, (long long)gpu_mb,
      max_resident <= budget ? "within" : "OVER", (long long)(cache.stats().evicted - evicted0),
      max_rss / 1e6);
  out["orbit"] = {{"dims", g0.dims},
                  {"levels", levels},
                  {"tree", eager ? "eager" : "coarse_first"},
                  {"open_s", t_file},
                  {"tree_first_s", tree_first_s},
                  {"first_picture_s", first_picture},
                  {"first_picture_cpu_s", first_picture_cpu},
                  {"tree_rest_cpu_s", tree_rest_cpu},
                  {"tree_rest_s", tree_rest_s},
                  {"load_s", load_s},
                  {"frame_ms", frame_ms},
                  {"frame_cpu_s", frame_cpu},
                  {"budget_mb", gpu_mb},
                  {"max_resident_mb", max_resident / 1048576.0},
                  {"max_rss_mb", max_rss / 1e6},
                  {"frames", frames}};
  if (max_resident > budget)
    throw Error(
        cat("orbit: the brick cache held ", max_resident, " bytes, over its budget of ", budget));
}

void paged_bench(const std::string& path, int size, std::int64_t gpu_mb, bool psnr, int reps,
                 const std::vector<Mode>& modes, std::optional<int> only_level,
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
  if (only_level && *only_level >= levels)
    throw UsageError(cat("--level ", *only_level, ": ", path, " has levels 0 to ", levels - 1));
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
    for (Mode m : modes) {
      RenderParams p = base;
      p.mode = m;
      p.slices_per_voxel = spv;
      if (m == Mode::kCt) p.opacity = 0.3;
      if (m == Mode::kIso) p.iso_hu = 300;
      const unsigned ch = channels_for(p, tree.present_channels());
      PlanOptions popt;
      popt.max_bytes = gpu_mb << 20;
      popt.border = viewer::BrickCache::kBorder;
      if (only_level) popt.finest_level = popt.coarsest_level = *only_level;
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
      const double cpu0 = cpu_seconds();
      Image8 img;
      viewer::FrameInfo info;
      const double ms = median_ms(reps, [&] {
        info = renderer.render_bricks(*cache, tree, plan, cam, p);
        img = renderer.read_rgba8();
      });
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
        const ForegroundDiff d = diff_foreground(img, ref);
        const double db = d.psnr_db;
        const int worst = d.max_diff;
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
    args.describe(
        "[--file X.vpk] [--size N] [--dims X,Y,Z] | --stack X,Y,Z --keep OUT.vpk | "
        "--orbit --file X.vpk [--eager-tree]",
        "Slice renderer benchmark.");
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
    bool no_paged = args.flag("--no-paged", "skip the brick-paged measurements");
    auto keep = args.option("--keep", "OUT.vpk", "write the synthetic volume there and keep it");
    std::string modes_text = args.option("--modes", "LIST", "paged modes, comma separated",
                                         "colour,ct,iso,labels,mip,tf2d");
    const int reps =
        int(args.option_int("--reps", "N", "frames timed per row (default 2)").value_or(2));
    auto stack = args.option("--stack", "X,Y,Z",
                             "write a synthetic stack slice by slice (with --keep) and stop");
    bool orbit_run = args.flag("--orbit", "first picture, a frame and a 36-frame orbit (--file)");
    bool eager = args.flag("--eager-tree", "--orbit: build every level's tree first (as before)");
    auto only_level = args.option_int(
        "--level", "L", "paged frames: draw level L only, whatever the screen footprint asks for");
    args.done();
    if (stack) {
      long long d[3];
      if (std::sscanf(stack->c_str(), "%lld,%lld,%lld", &d[0], &d[1], &d[2]) != 3 || d[0] < 1 ||
          d[1] < 1 || d[2] < 1)
        throw UsageError("--stack must be X,Y,Z (positive)");
      if (!keep) throw UsageError("--stack needs --keep OUT.vpk");
      const double t0 = now();
      write_stack(*keep, d[0], d[1], d[2], black_slices(d[2]));
      std::printf("stack %lldx%lldx%lld written to %s in %.1f s (%.2f GB)\n", d[0], d[1], d[2],
                  keep->c_str(), now() - t0, double(std::filesystem::file_size(*keep)) / 1e9);
      return 0;
    }
    if (orbit_run) {
      if (!file) throw UsageError("--orbit needs --file X.vpk");
      nlohmann::json out;
      std::setvbuf(stdout, nullptr, _IOLBF, 0);
      orbit_bench(*file, int(size_opt.value_or(512)), gpu_mb.value_or(2048), eager, reps, out);
      if (json_out) write_file_atomic(*json_out, out.dump(1));
      return 0;
    }
    if (reps < 1) throw UsageError("--reps must be at least 1");
    if (paged_only && no_paged) throw UsageError("--paged-only and --no-paged exclude each other");
    auto split = [](const std::string& text) {
      std::vector<std::string> items;
      for (std::size_t pos = 0; pos <= text.size();) {
        std::size_t end = text.find(',', pos);
        if (end == std::string::npos) end = text.size();
        items.push_back(text.substr(pos, end - pos));
        pos = end + 1;
      }
      return items;
    };
    std::vector<double> spv;
    for (const std::string& item : split(spv_text)) {
      const double v = std::atof(item.c_str());
      if (!(v > 0)) throw UsageError("--spv must list positive numbers");
      spv.push_back(v);
    }
    std::vector<Mode> modes;
    for (const std::string& item : split(modes_text)) {
      const std::optional<Mode> m = mode_from_name(item);
      if (!m) throw UsageError("--modes: unknown mode '" + item + "'");
      modes.push_back(*m);
    }
    nlohmann::json out;
    std::setvbuf(stdout, nullptr, _IOLBF, 0);  // lines appear as they are measured
    int size = int(size_opt.value_or(256));
    std::string path;
    std::filesystem::path tmp;
    // The synthetic volume's temporary folder goes on any exit, an error's too.
    struct RemoveFolder {
      const std::filesystem::path& folder;
      ~RemoveFolder() {
        std::error_code ec;
        if (!folder.empty()) std::filesystem::remove_all(folder, ec);
      }
    } remove_tmp{tmp};
    if (file) {
      path = *file;
    } else {
      int d[3];
      if (std::sscanf(dims_text.c_str(), "%d,%d,%d", &d[0], &d[1], &d[2]) != 3)
        throw UsageError("--dims must be X,Y,Z");
      if (keep) {
        path = *keep;
      } else {
        tmp = std::filesystem::temp_directory_path() / ("viewer_bench_" + std::to_string(getpid()));
        std::filesystem::create_directories(tmp);
        path = (tmp / "medium.vpk").string();
      }
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

    std::optional<int> level;
    if (only_level) {
      if (*only_level < 0) throw UsageError("--level must be 0 or more");
      level = int(*only_level);
    }
    if (!no_paged)
      paged_bench(path, size, gpu_mb.value_or(2048), paged_psnr, reps, modes, level, out);
    if (paged_only) {
      if (json_out) write_file_atomic(*json_out, out.dump(1));
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
        "\n| mode | slices/voxel | slices | frame time (ms, %dx%d, median of %d) | foreground "
        "PSNR vs reference (dB) | max diff | whole-frame PSNR (dB) "
        "|\n|---|---|---|---|---|---|---|\n",
        size, size, reps);
    out["reps"] = reps;
    out["reference"] = "CPU reference ray caster, 8 steps per voxel, level 0";
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
        Image8 img;
        const double ms = median_ms(reps, [&] {
          renderer.render(fine, cam, p);
          img = renderer.read_rgba8();
        });
        rows.push_back(quality_row(mode_name(m), 0, s, info.slices, ms, img, ref));
      }
      // Levels of detail: the coarser levels' textures, 1 slice per voxel of that level.
      for (int level = 1; json_out && m == Mode::kColour && level < source->level_count();
           ++level) {
        viewer::VolumeTextures lod;
        lod.upload(*source, level, 0);
        p.slices_per_voxel = 1.0;
        viewer::FrameInfo info = renderer.render(lod, cam, p);  // warm-up
        renderer.read_rgba8();
        Image8 img;
        const double ms = median_ms(reps, [&] {
          renderer.render(lod, cam, p);
          img = renderer.read_rgba8();
        });
        rows.push_back(quality_row(mode_name(m), level, 1.0, info.slices, ms, img, ref));
      }
      std::fprintf(stderr, "(reference %s: %.1f s)\n", mode_name(m), t_ref);
    }
    out["rows"] = rows;
    if (json_out) write_file_atomic(*json_out, out.dump(1));
    return 0;
  });
}

// Format benchmark: prints markdown tables for docs/BENCHMARKS.md "## Format".
//
//   build/bin/format_bench [--size N] [--sweep-size M] [--threads T] [--dir DIR]
//
// Synthetic volume resembling the data: smooth CT-like int16 with noise (air outside the body),
// RGBA body in blue gel (alpha 0 in the gel), piecewise-constant labels; N^3 voxels (default 256:
// 112 MB over the three channels). Measures, in one run:
//   * pack throughput vs `zstd -3 -T<threads>` on the same raw bytes (ratio), read throughput vs
//     `zstd -d`, random-brick decode latency;
//   * stored size vs raw and vs an OpenVDB file of the same data (default Blosc compression);
//   * brick edge 32/64/128 x zstd level 1/3/9/19 on an M^3 volume (default 128);
//   * the writer's peak RSS as the volume grows in z (must stay flat), each size in a child
//   process.
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/format/format.h"

#ifdef VISPACK_BENCH_HAVE_OPENVDB
#include <openvdb/openvdb.h>
#endif

using namespace vispack;
using namespace vispack::format;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

// One z slice of the synthetic volume (rgba8, int16 HU, uint16 labels), deterministic in z.
void make_slice(std::int64_t nx, std::int64_t ny, std::int64_t nz, std::int64_t z,
                std::uint8_t* rgba, std::int16_t* ct, std::uint16_t* labels) {
  std::mt19937 rng(std::uint32_t(1234 + z));
  std::normal_distribution<double> noise(0.0, 12.0);
  const double cx = nx / 2.0, cy = ny / 2.0, cz = nz / 2.0;
  for (std::int64_t y = 0; y < ny; ++y) {
    for (std::int64_t x = 0; x < nx; ++x) {
      const std::size_t i = std::size_t(y * nx + x);
      double rx = (x - cx) / (0.38 * nx), ry = (y - cy) / (0.3 * ny), rz = (z - cz) / (0.48 * nz);
      double r2 = rx * rx + ry * ry + rz * rz;
      if (r2 < 1.0) {
        // Organs: nested shells and a few blobs with distinct HU and colour.
        int organ = r2 > 0.85  ? 1
                    : r2 > 0.7 ? 2
                               : (int(std::floor(4 * rx + 2 * ry + 3 * rz)) & 7) + 3;
        if (std::abs(rx - 0.3) < 0.12 && std::abs(ry) < 0.5) organ = 11;  // a "bone"
        static const int hu[12] = {0, -100, 40, 30, 45, 60, 20, 35, 50, -700, 0, 900};
        double v = hu[organ] + 25 * std::sin(0.05 * x + 0.03 * z) + noise(rng);
        ct[i] = std::int16_t(std::lround(v));
        rgba[4 * i + 0] = std::uint8_t(std::clamp(150 + organ * 7 + noise(rng) * 0.5, 0.0, 255.0));
        rgba[4 * i + 1] = std::uint8_t(std::clamp(80 + organ * 5 + noise(rng) * 0.5, 0.0, 255.0));
        rgba[4 * i + 2] = std::uint8_t(std::clamp(60 + organ * 3 + noise(rng) * 0.5, 0.0, 255.0));
        rgba[4 * i + 3] = 255;
        labels[i] = std::uint16_t(organ);
      } else {
        ct[i] = std::int16_t(-1000 + std::lround(noise(rng) * 0.2));  // air with a little noise
        rgba[4 * i + 0] = 30;
        rgba[4 * i + 1] = 60;
        rgba[4 * i + 2] = std::uint8_t(std::clamp(170 + noise(rng) * 0.3, 0.0, 255.0));  // blue gel
        rgba[4 * i + 3] = 0;
        labels[i] = 0;
      }
    }
  }
}

struct Synthetic {
  std::int64_t nx, ny, nz;
  std::vector<std::uint8_t> rgba;
  std::vector<std::int16_t> ct;
  std::vector<std::uint16_t> labels;
};

Synthetic make_volume(std::int64_t nx, std::int64_t ny, std::int64_t nz) {
  Synthetic s{nx, ny, nz, {}, {}, {}};
  const std::size_t plane = std::size_t(nx * ny);
  s.rgba.resize(plane * std::size_t(nz) * 4);
  s.ct.resize(plane * std::size_t(nz));
  s.labels.resize(plane * std::size_t(nz));
  for (std::int64_t z = 0; z < nz; ++z) {
    make_slice(nx, ny, nz, z, &s.rgba[plane * 4 * std::size_t(z)], &s.ct[plane * std::size_t(z)],
               &s.labels[plane * std::size_t(z)]);
  }
  return s;
}

WriterOptions options(std::int64_t nx, std::int64_t ny, std::int64_t nz, int edge, int level,
                      int threads) {
  WriterOptions o;
  o.dims = {nx, ny, nz};
  o.brick_edge = edge;
  o.zstd_level = level;
  o.threads = threads;
  o.channels = {
      {"rgba", ChannelType::kRgba8}, {"ct", ChannelType::kInt16}, {"labels", ChannelType::kUint16}};
  for (std::uint32_t id = 1; id <= 11; ++id)
    o.label_table.push_back({id, "organ" + std::to_string(id), {}});
  return o;
}

void pack(const std::string& path, const Synthetic& s, const WriterOptions& o) {
  write_volume(path, o, {s.rgba.data(), s.ct.data(), s.labels.data()});
}

double run_seconds(const std::string& command) {
  auto t = Clock::now();
  int rc = std::system(command.c_str());
  if (rc != 0) throw Error(cat("command failed: ", command));
  return seconds_since(t);
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

std::uint64_t file_size(const std::string& p) {
  return std::filesystem::file_size(p);
}

// Peak RSS (MiB) of a child process that streams an nx*ny*nz volume through a Writer.
double writer_peak_rss_mib(const std::string& path, std::int64_t nx, std::int64_t ny,
                           std::int64_t nz, int threads) {
  int fds[2];
  if (::pipe(fds) != 0) throw IoError("pipe failed");
  pid_t pid = ::fork();
  if (pid == 0) {
    ::close(fds[0]);
    double mib = -1;
    try {
      const std::size_t plane = std::size_t(nx * ny);
      std::vector<std::uint8_t> rgba(plane * 4);
      std::vector<std::int16_t> ct(plane);
      std::vector<std::uint16_t> labels(plane);
      Writer w(path, options(nx, ny, nz, 64, 3, threads));
      for (std::int64_t z = 0; z < nz; ++z) {
        make_slice(nx, ny, nz, z, rgba.data(), ct.data(), labels.data());
        w.append_slice({rgba.data(), ct.data(), labels.data()});
      }
      w.finish();
      rusage ru{};
      ::getrusage(RUSAGE_SELF, &ru);
      mib = ru.ru_maxrss / 1024.0;
    } catch (...) {
    }
    ssize_t ignored = ::write(fds[1], &mib, sizeof(mib));
    (void)ignored;
    ::_exit(0);
  }
  ::close(fds[1]);
  double mib = -1;
  ssize_t n = ::read(fds[0], &mib, sizeof(mib));
  ::close(fds[0]);
  int status = 0;
  ::waitpid(pid, &status, 0);
  if (n != sizeof(mib) || mib < 0) throw Error("writer child failed");
  return mib;
}

#ifdef VISPACK_BENCH_HAVE_OPENVDB
// The same data as OpenVDB grids (ct FloatGrid background -1000, labels Int32Grid background 0,
// colour Vec3SGrid active where alpha > 0), written with OpenVDB's default compression (Blosc).
std::uint64_t openvdb_size(const std::string& path, const Synthetic& s) {
  openvdb::initialize();
  auto ct = openvdb::FloatGrid::create(-1000.0f);
  auto labels = openvdb::Int32Grid::create(0);
  auto colour = openvdb::Vec3SGrid::create(openvdb::Vec3s(0, 0, 0));
  ct->setName("ct");
  labels->setName("labels");
  colour->setName("rgb");
  auto cta = ct->getAccessor();
  auto la = labels->getAccessor();
  auto ca = colour->getAccessor();
  for (std::int64_t z = 0; z < s.nz; ++z)
    for (std::int64_t y = 0; y < s.ny; ++y)
      for (std::int64_t x = 0; x < s.nx; ++x) {
        std::size_t i = std::size_t((z * s.ny + y) * s.nx + x);
        const openvdb::Coord c{int(x), int(y), int(z)};
        if (s.ct[i] != -1000) cta.setValue(c, float(s.ct[i]));
        if (s.labels[i] != 0) la.setValue(c, int(s.labels[i]));
        if (s.rgba[4 * i + 3] > 0) {
          ca.setValue(c, openvdb::Vec3s(s.rgba[4 * i] / 255.f, s.rgba[4 * i + 1] / 255.f,
                                        s.rgba[4 * i + 2] / 255.f));
        }
      }
  openvdb::GridPtrVec grids{ct, labels, colour};
  openvdb::io::File(path).write(grids);
  return file_size(path);
}
#endif

}  // namespace

int main(int argc, char** argv) {
  return run_main("format_bench", argc, argv, [](Args& args) {
    args.describe("[--size N] [--sweep-size M] [--threads T] [--dir DIR]",
                  "Benchmarks the packed format; prints markdown tables.");
    const std::int64_t n =
        args.option_int("--size", "N", "main volume edge in voxels (default 256)").value_or(256);
    const std::int64_t m =
        args.option_int("--sweep-size", "M", "edge of the sweep volume (default 128)")
            .value_or(128);
    const int threads =
        int(args.option_int("--threads", "T", "writer/zstd threads (default 2)").value_or(2));
    const std::string dir =
        args.option("--dir", "DIR", "scratch folder", "/tmp/vispack_format_bench");
    args.done();
    std::filesystem::create_directories(dir);
    const std::string vpk = dir + "/bench.vpk", raw = dir + "/bench.raw",
                      zst = dir + "/bench.raw.zst";

    Synthetic s = make_volume(n, n, n);
    const double raw_mb = (s.rgba.size() + s.ct.size() * 2 + s.labels.size() * 2) / 1e6;
    {
      std::ofstream out(raw, std::ios::binary);
      out.write(reinterpret_cast<const char*>(s.rgba.data()), std::streamsize(s.rgba.size()));
      out.write(reinterpret_cast<const char*>(s.ct.data()), std::streamsize(s.ct.size() * 2));
      out.write(reinterpret_cast<const char*>(s.labels.data()),
                std::streamsize(s.labels.size() * 2));
    }
    // Labels are stored as uint8 (max id 11), so raw bytes fed to zstd include the uint16 labels:
    // zstd gets slightly more input (the same information).
    std::vector<double> t_pack, t_zstd, t_read1, t_read2, t_unzstd;
    for (int rep = 0; rep < 3; ++rep) {
      auto t = Clock::now();
      pack(vpk, s, options(n, n, n, 64, 3, threads));
      t_pack.push_back(seconds_since(t));
      t_zstd.push_back(run_seconds(cat("zstd -q -f -3 -T", threads, " ", raw, " -o ", zst)));
      Reader r = Reader::open(vpk);
      t = Clock::now();
      for (int c = 0; c < 3; ++c)
        r.read_level(c, 0, 1);
      t_read1.push_back(seconds_since(t));
      t = Clock::now();
      for (int c = 0; c < 3; ++c)
        r.read_level(c, 0, threads);
      t_read2.push_back(seconds_since(t));
      t_unzstd.push_back(run_seconds(cat("zstd -q -d -c ", zst, " > /dev/null")));
    }
    Reader r = Reader::open(vpk);
    // Random level-0 brick latency (decode into a caller buffer), per channel.
    std::mt19937 rng(7);
    std::printf(
        "### Throughput (%lldx%lldx%lld, rgba+ct+labels = %.0f MB raw, edge 64, zstd 3, %d "
        "threads; median of 3)\n\n",
        (long long)n, (long long)n, (long long)n, raw_mb, threads);
    std::printf("| measure | vispack | zstd CLI | vispack / zstd time |\n|---|---|---|---|\n");
    std::printf(
        "| pack (incl. mip pyramid, stats, checksums) | %.2f s (%.0f MB/s) | `zstd -3 -T%d`: %.2f "
        "s (%.0f MB/s) | %.2f |\n",
        median(t_pack), raw_mb / median(t_pack), threads, median(t_zstd), raw_mb / median(t_zstd),
        median(t_pack) / median(t_zstd));
    std::printf(
        "| read level 0, 1 thread | %.2f s (%.0f MB/s) | `zstd -d`: %.2f s (%.0f MB/s) | %.2f |\n",
        median(t_read1), raw_mb / median(t_read1), median(t_unzstd), raw_mb / median(t_unzstd),
        median(t_read1) / median(t_unzstd));
    std::printf("| read level 0, %d threads | %.2f s (%.0f MB/s) | | %.2f |\n", threads,
                median(t_read2), raw_mb / median(t_read2), median(t_read2) / median(t_unzstd));
    std::printf(
        "\n| channel | random level-0 brick decode, median | p99 | stored (all levels) | level-0 "
        "raw | raw / stored |\n|---|---|---|---|---|---|\n");
    for (int c = 0; c < 3; ++c) {
      const LevelInfo& li = r.level(0);
      std::vector<std::uint8_t> buf(r.brick_bytes(c));
      std::vector<double> lat;
      for (int i = 0; i < 300; ++i) {
        std::int64_t bx = rng() % li.bricks[0], by = rng() % li.bricks[1],
                     bz = rng() % li.bricks[2];
        auto t = Clock::now();
        r.decode_brick(r.brick(c, 0, bx, by, bz), buf.data(), buf.size());
        lat.push_back(seconds_since(t) * 1e6);
      }
      std::sort(lat.begin(), lat.end());
      std::uint64_t stored = 0;
      for (const BrickInfo& b : r.bricks())
        if (b.channel == c) stored += b.stored_size;
      const double level0 =
          double(n * n * n) * channel_type_bytes(r.channels()[std::size_t(c)].type);
      std::printf("| %s (%s) | %.0f us | %.0f us | %.2f MB | %.2f MB | %.1f |\n",
                  r.channels()[std::size_t(c)].name.c_str(),
                  channel_type_name(r.channels()[std::size_t(c)].type), lat[lat.size() / 2],
                  lat[lat.size() * 99 / 100], stored / 1e6, level0 / 1e6,
                  level0 / std::max<double>(1, stored));
    }
    std::printf("\n### Stored size\n\n| file | bytes | vs raw input (%.0f MB) |\n|---|---|---|\n",
                raw_mb);
    std::printf(
        "| vispack .vpk (edge 64, zstd 3, all levels, uint8 labels) | %.2f MB | %.1fx smaller |\n",
        file_size(vpk) / 1e6, raw_mb * 1e6 / file_size(vpk));
    std::printf("| `zstd -3` of the raw bytes (level 0 only) | %.2f MB | %.1fx smaller |\n",
                file_size(zst) / 1e6, raw_mb * 1e6 / file_size(zst));
#ifdef VISPACK_BENCH_HAVE_OPENVDB
    {
      const std::string vdb = dir + "/bench.vdb";
      std::uint64_t bytes = openvdb_size(vdb, s);
      std::printf(
          "| OpenVDB 10 (default Blosc; ct float, labels int32, rgb vec3s, level 0 only) | %.2f MB "
          "| %.1fx smaller |\n",
          bytes / 1e6, raw_mb * 1e6 / bytes);
    }
#endif
    // Sweep: brick edge x zstd level on a smaller volume.
    Synthetic w = make_volume(m, m, m);
    const double w_mb =
        (w.rgba.size() + w.ct.size() * 2 + w.labels.size()) / 1e6;  // labels stored uint8
    std::printf(
        "\n### Brick edge x zstd level (%lldx%lldx%lld, %.1f MB as stored types, %d threads)\n\n",
        (long long)m, (long long)m, (long long)m, w_mb, threads);
    std::printf(
        "| edge | zstd level | pack MB/s | file MB | level-0 raw / file | read MB/s (1 thread) | "
        "random brick us |\n|---|---|---|---|---|---|---|\n");
    for (int edge : {32, 64, 128}) {
      for (int level : {1, 3, 9, 19}) {
        const std::string p = dir + "/sweep.vpk";
        auto t = Clock::now();
        pack(p, w, options(m, m, m, edge, level, threads));
        double tp = seconds_since(t);
        Reader rr = Reader::open(p);
        t = Clock::now();
        for (int c = 0; c < 3; ++c)
          rr.read_level(c, 0, 1);
        double tr = seconds_since(t);
        std::vector<std::uint8_t> buf(rr.brick_bytes(0));
        std::vector<double> lat;
        const LevelInfo& li = rr.level(0);
        for (int i = 0; i < 50; ++i) {
          auto t2 = Clock::now();
          rr.decode_brick(
              rr.brick(0, 0, rng() % li.bricks[0], rng() % li.bricks[1], rng() % li.bricks[2]),
              buf.data(), buf.size());
          lat.push_back(seconds_since(t2) * 1e6);
        }
        std::printf("| %d | %d | %.0f | %.2f | %.1f | %.0f | %.0f |\n", edge, level, w_mb / tp,
                    file_size(p) / 1e6, w_mb * 1e6 / file_size(p), w_mb / tr, median(lat));
      }
    }
    // Writer memory as the volume grows in z (streamed slices, child process per size).
    std::printf(
        "\n### Writer peak RSS as the volume grows (%lldx%lld slices streamed, edge 64, %d "
        "threads)\n\n| slices | raw MB | peak RSS MiB |\n|---|---|---|\n",
        (long long)n, (long long)n, threads);
    s = Synthetic{};  // free the big volume before measuring
    for (std::int64_t nz : {64, 128, 256, 512, 1024}) {
      double mib = writer_peak_rss_mib(dir + "/mem.vpk", n, n, nz, threads);
      std::printf("| %lld | %.0f | %.0f |\n", (long long)nz, double(n * n * nz) * 8 / 1e6, mib);
    }
    std::filesystem::remove_all(dir);
    return 0;
  });
}

// Format benchmark: prints markdown tables for docs/BENCHMARKS.md "## Format".
//
//   build/bin/format_bench [--size N] [--sweep-size M] [--threads T] [--reps R] [--dir DIR]
//
// Synthetic volume resembling the data: smooth CT-like int16 with noise (air outside the body),
// RGBA body in blue gel (alpha 0 in the gel), piecewise-constant labels; N^3 voxels (default 256:
// 112 MB over the three channels). Measures, in one run:
//   * pack and read throughput against libzstd called in-process on the same brick bytes at the
//     same level and thread count (ZSTD_compressCCtx / ZSTD_decompressDCtx per brick, one context
//     per thread), runs interleaved (vispack, libzstd, vispack, libzstd, ...), medians and ratio;
//     random-brick decode latency against ZSTD_decompressDCtx of the same brick;
//   * stored size vs raw and vs an OpenVDB file of the same data (default Blosc compression);
//   * brick edge 32/64/128 x zstd level 1/3/9/19 on an M^3 volume (default 128);
//   * the writer's peak RSS as the volume grows in z (must stay flat), each size in a child
//   process.
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <zstd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <random>
#include <string>
#include <thread>
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

// The peer: libzstd in-process on the bytes vispack compresses. `bricks` holds every brick of
// the file decoded (all levels, all channels, uniform ones included, as zstd would not know
// them); compress() compresses each one with ZSTD_compressCCtx at `level` on `threads` threads
// (one context each), decompress() decodes the level-0 ones back with ZSTD_decompressDCtx.
struct ZstdPeer {
  std::vector<std::vector<std::uint8_t>> bricks, packed;
  std::vector<bool> level0;
  ZSTD_DCtx* latency_dctx = ZSTD_createDCtx();  // for decompress_one (one brick at a time)

  // Runs body(i, ctx) for every i in [0, n) on `threads` threads; each thread makes its own zstd
  // context with make() and frees it with release() afterwards, as the writer's workers do.
  template <class Make, class Release, class F>
  static void parallel(std::size_t n, int threads, Make make, Release release, F body) {
    std::atomic<std::size_t> next{0};
    std::exception_ptr failed;
    std::mutex failed_mutex;
    auto work = [&] {
      auto* ctx = make();
      try {
        for (std::size_t i; (i = next++) < n;)
          body(i, ctx);
      } catch (...) {
        std::lock_guard<std::mutex> lock(failed_mutex);
        if (!failed) failed = std::current_exception();
        next = n;
      }
      release(ctx);
    };
    std::vector<std::thread> pool;
    for (int t = 1; t < threads; ++t)
      pool.emplace_back(work);
    work();
    for (std::thread& t : pool)
      t.join();
    if (failed) std::rethrow_exception(failed);
  }

  explicit ZstdPeer(const Reader& r) {
    for (const BrickInfo& b : r.bricks()) {
      bricks.emplace_back(r.brick_bytes(b.channel));
      r.decode_brick(b, bricks.back().data(), bricks.back().size());
      level0.push_back(b.level == 0);
    }
    packed.resize(bricks.size());
  }
  ZstdPeer(const ZstdPeer&) = delete;
  ZstdPeer& operator=(const ZstdPeer&) = delete;
  ~ZstdPeer() { ZSTD_freeDCtx(latency_dctx); }

  // Returns the compressed bytes of the level-0 bricks.
  std::uint64_t compress(int level, int threads) {
    parallel(
        bricks.size(), threads, [] { return ZSTD_createCCtx(); },
        [](ZSTD_CCtx* c) { ZSTD_freeCCtx(c); },
        [&, level](std::size_t i, ZSTD_CCtx* cctx) {
          packed[i].resize(ZSTD_compressBound(bricks[i].size()));
          std::size_t n = ZSTD_compressCCtx(cctx, packed[i].data(), packed[i].size(),
                                            bricks[i].data(), bricks[i].size(), level);
          if (ZSTD_isError(n)) throw Error(cat("ZSTD_compressCCtx: ", ZSTD_getErrorName(n)));
          packed[i].resize(n);
        });
    std::uint64_t bytes = 0;
    for (std::size_t i = 0; i < packed.size(); ++i)
      if (level0[i]) bytes += packed[i].size();
    return bytes;
  }

  void decompress_one(std::size_t i, std::uint8_t* out, ZSTD_DCtx* dctx) const {
    std::size_t n =
        ZSTD_decompressDCtx(dctx, out, bricks[i].size(), packed[i].data(), packed[i].size());
    if (ZSTD_isError(n) || n != bricks[i].size()) throw Error("ZSTD_decompressDCtx failed");
  }
  void decompress_one(std::size_t i, std::uint8_t* out) const {
    decompress_one(i, out, latency_dctx);
  }

  // Decodes every level-0 brick into its own buffer (no assembly into a dense volume).
  void decompress(int threads, std::vector<std::vector<std::uint8_t>>& out) const {
    out.resize(bricks.size());
    parallel(
        bricks.size(), threads, [] { return ZSTD_createDCtx(); },
        [](ZSTD_DCtx* d) { ZSTD_freeDCtx(d); },
        [&](std::size_t i, ZSTD_DCtx* dctx) {
          if (!level0[i]) return;
          out[i].resize(bricks[i].size());
          decompress_one(i, out[i].data(), dctx);
        });
  }
};

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
    args.describe("[--size N] [--sweep-size M] [--threads T] [--reps R] [--dir DIR]",
                  "Benchmarks the packed format; prints markdown tables.");
    const std::int64_t n =
        args.option_int("--size", "N", "main volume edge in voxels (default 256)").value_or(256);
    const std::int64_t m =
        args.option_int("--sweep-size", "M", "edge of the sweep volume (default 128)")
            .value_or(128);
    const int threads =
        int(args.option_int("--threads", "T", "writer/zstd threads (default 2)").value_or(2));
    const int reps = std::max(
        1, int(args.option_int("--reps", "R", "interleaved repetitions (default 5)").value_or(5)));
    const std::string dir =
        args.option("--dir", "DIR", "scratch folder", "/tmp/vispack_format_bench");
    args.done();
    std::filesystem::create_directories(dir);
    const std::string vpk = dir + "/bench.vpk";

    Synthetic s = make_volume(n, n, n);
    const double raw_mb = (s.rgba.size() + s.ct.size() * 2 + s.labels.size() * 2) / 1e6;
    // The peer compresses the bytes vispack compresses: every brick of the file, decoded (labels
    // are stored as uint8, max id 11, so these are fewer bytes than the uint16 input; MB/s below
    // is the raw input MB over the time for both, as before).
    pack(vpk, s, options(n, n, n, 64, 3, threads));
    ZstdPeer peer(Reader::open(vpk));
    std::uint64_t zstd_level0_bytes = 0;
    std::vector<std::vector<std::uint8_t>> scratch;
    std::vector<double> t_pack, t_zstd, t_read1, t_read2, t_unzstd1, t_unzstd2;
    // Interleaved: each repetition runs vispack then libzstd for every measure, so both see the
    // same machine load; medians over the repetitions.
    for (int rep = 0; rep < reps; ++rep) {
      auto t = Clock::now();
      pack(vpk, s, options(n, n, n, 64, 3, threads));
      t_pack.push_back(seconds_since(t));
      t = Clock::now();
      zstd_level0_bytes = peer.compress(3, threads);
      t_zstd.push_back(seconds_since(t));
      Reader r = Reader::open(vpk);
      t = Clock::now();
      for (int c = 0; c < 3; ++c)
        r.read_level(c, 0, 1);
      t_read1.push_back(seconds_since(t));
      t = Clock::now();
      peer.decompress(1, scratch);
      t_unzstd1.push_back(seconds_since(t));
      t = Clock::now();
      for (int c = 0; c < 3; ++c)
        r.read_level(c, 0, threads);
      t_read2.push_back(seconds_since(t));
      t = Clock::now();
      peer.decompress(threads, scratch);
      t_unzstd2.push_back(seconds_since(t));
    }
    scratch.clear();
    std::printf(
        "### Throughput (%lldx%lldx%lld, rgba+ct+labels = %.0f MB raw, edge 64, zstd 3, %d "
        "threads; vispack and libzstd interleaved, median of %d)\n\n",
        (long long)n, (long long)n, (long long)n, raw_mb, threads, reps);
    std::printf(
        "Peer: libzstd %s in this process on the same bytes: every brick of the .vpk (all "
        "levels, uniform bricks included), decoded, compressed one by one with "
        "`ZSTD_compressCCtx` at level 3 on the same thread count (one context per thread), and "
        "the level-0 ones decompressed with `ZSTD_decompressDCtx` into per-brick buffers. vispack "
        "also builds the pyramid, statistics and checksums and writes the file (pack), and "
        "assembles the bricks into one dense array per channel (read); the peer does neither.\n\n",
        ZSTD_versionString());
    std::printf(
        "| measure | vispack | libzstd in-process | vispack / libzstd time |\n|---|---|---|---|\n");
    auto row = [&](const char* what, const std::vector<double>& ours, const std::string& peer_name,
                   const std::vector<double>& theirs) {
      std::printf("| %s | %.2f s (%.0f MB/s) | %s: %.2f s (%.0f MB/s) | %.2f |\n", what,
                  median(ours), raw_mb / median(ours), peer_name.c_str(), median(theirs),
                  raw_mb / median(theirs), median(ours) / median(theirs));
    };
    row("pack (incl. mip pyramid, stats, checksums, file)", t_pack,
        cat("`ZSTD_compressCCtx` level 3, ", threads, " threads"), t_zstd);
    row("read level 0, 1 thread", t_read1, "`ZSTD_decompressDCtx`, 1 thread", t_unzstd1);
    row(cat("read level 0, ", threads, " threads").c_str(), t_read2,
        cat("`ZSTD_decompressDCtx`, ", threads, " threads"), t_unzstd2);
    Reader r = Reader::open(vpk);
    // The peer's bricks are in r.bricks() order (the files are identical, deterministic writer).
    const BrickInfo* first = r.bricks().data();
    // Random level-0 brick latency (decode into a caller buffer), per channel.
    std::mt19937 rng(7);
    std::printf(
        "\n| channel | random level-0 brick decode, median | p99 | libzstd "
        "`ZSTD_decompressDCtx` of the same bricks, median | stored (all levels) | level-0 raw | "
        "raw / stored |\n|---|---|---|---|---|---|---|\n");
    for (int c = 0; c < 3; ++c) {
      const LevelInfo& li = r.level(0);
      std::vector<std::uint8_t> buf(r.brick_bytes(c));
      std::vector<double> lat, zlat;
      for (int i = 0; i < 300; ++i) {  // interleaved: vispack's decode, then libzstd's
        std::int64_t bx = rng() % li.bricks[0], by = rng() % li.bricks[1],
                     bz = rng() % li.bricks[2];
        const BrickInfo& b = r.brick(c, 0, bx, by, bz);
        auto t = Clock::now();
        r.decode_brick(b, buf.data(), buf.size());
        lat.push_back(seconds_since(t) * 1e6);
        t = Clock::now();
        peer.decompress_one(std::size_t(&b - first), buf.data());
        zlat.push_back(seconds_since(t) * 1e6);
      }
      std::sort(lat.begin(), lat.end());
      std::uint64_t stored = 0;
      for (const BrickInfo& b : r.bricks())
        if (b.channel == c) stored += b.stored_size;
      const double level0 =
          double(n * n * n) * channel_type_bytes(r.channels()[std::size_t(c)].type);
      std::printf("| %s (%s) | %.0f us | %.0f us | %.0f us | %.2f MB | %.2f MB | %.1f |\n",
                  r.channels()[std::size_t(c)].name.c_str(),
                  channel_type_name(r.channels()[std::size_t(c)].type), lat[lat.size() / 2],
                  lat[lat.size() * 99 / 100], median(zlat), stored / 1e6, level0 / 1e6,
                  level0 / std::max<double>(1, stored));
    }
    std::printf("\n### Stored size\n\n| file | bytes | vs raw input (%.0f MB) |\n|---|---|---|\n",
                raw_mb);
    std::printf(
        "| vispack .vpk (edge 64, zstd 3, all levels, uint8 labels) | %.2f MB | %.1fx smaller |\n",
        file_size(vpk) / 1e6, raw_mb * 1e6 / file_size(vpk));
    std::printf(
        "| libzstd level 3 of the same level-0 bricks (uint8 labels), payload only | %.2f MB | "
        "%.1fx smaller |\n",
        zstd_level0_bytes / 1e6, raw_mb * 1e6 / double(zstd_level0_bytes));
#ifdef VISPACK_BENCH_HAVE_OPENVDB
    {
      const std::string vdb = dir + "/bench.vdb";
      std::uint64_t bytes = openvdb_size(vdb, s);
      std::printf(
          "| OpenVDB 10 file written here with OpenVDB's own writer, other content (default "
          "Blosc; ct float, labels int32, rgb vec3s without alpha, level 0 only, non-background "
          "voxels only) | %.2f MB | %.1fx smaller |\n",
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

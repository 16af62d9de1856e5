// The pack's encoder on the level-0 bytes alone: what `zstd -3 -T2` of the same bytes is
// compared with (scripts/bench/real_size.py). Reads the level-0 channels of a packed
// file as `vispack-extract --channel C` wrote them (NRRD, one per channel, in the file's channel
// order) into memory, then times a format::Writer fed those slices with the packed file's
// options (dims, spacing, origin, brick edge, channels, label table; zstd level and threads as
// given): every level, statistics, checksums and the file, as vispack-pack writes them. The
// NRRD reading is timed apart. Prints one JSON line. With VISPACK_PERF_CTL naming a perf control
// FIFO, writes "enable" to it when the timed part starts (profile the Writer alone).
//
//   build/bin/format_writer_raw_bench TEMPLATE.vpk OUT.vpk CHANNEL.nrrd... [--zstd-level L]
//       [--threads T] [--repeat N] [--brick-edge E]
// --brick-edge E writes bricks of E (the Writer checks it) instead of the template's.
// --repeat N feeds the slices N times over (0..nz-1, 0..nz-1, ...: a stack N times as deep, whose
// level-0 bytes are each NRRD's data N times over, the peer's input), to measure the encoder past
// its first slabs (the first fill of a fresh slab pays its page faults) without holding N times
// the bytes in memory.
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/common/nrrd.h"
#include "vispack/format/format.h"

using namespace vispack;
using Clock = std::chrono::steady_clock;

namespace {

// User and system CPU seconds of the process so far.
std::pair<double, double> cpu_seconds() {
  struct rusage usage {};
  getrusage(RUSAGE_SELF, &usage);
  return {double(usage.ru_utime.tv_sec) + 1e-6 * double(usage.ru_utime.tv_usec),
          double(usage.ru_stime.tv_sec) + 1e-6 * double(usage.ru_stime.tv_usec)};
}

double since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

}  // namespace

int main(int argc, char** argv) {
  return run_main("format_writer_raw_bench", argc, argv, [](Args& args) {
    args.describe(
        "TEMPLATE.vpk OUT.vpk CHANNEL.nrrd... [--zstd-level L] [--threads T] [--repeat N] "
        "[--brick-edge E]",
        "Times the format Writer on a packed file's level-0 bytes (vispack-extract "
        "NRRDs, one per channel in the file's order) with the file's options.");
    const int zstd_level =
        int(args.option_int("--zstd-level", "L", "zstd level (default 3)").value_or(3));
    const int threads = int(args.option_int("--threads", "T", "threads (default 2)").value_or(2));
    const int repeat = int(
        args.option_int("--repeat", "N", "feed the slices N times over (default 1)").value_or(1));
    if (repeat < 1) throw UsageError("--repeat must be at least 1");
    const auto brick_edge =
        args.option_int("--brick-edge", "E", "brick edge (default: the template's)");
    const std::string template_path = args.positional("TEMPLATE.vpk", "packed file (options)");
    const std::string out_path = args.positional("OUT.vpk", "output packed file");
    std::vector<std::string> inputs;
    for (;;) {
      std::string more = args.positional("CHANNEL.nrrd", "a channel's level 0", true);
      if (more.empty()) break;
      inputs.push_back(more);
    }
    args.done();

    const format::Reader tmpl = format::Reader::open(template_path);
    if (inputs.size() != tmpl.channels().size())
      throw UsageError(cat("one NRRD per channel: ", template_path, " has ", tmpl.channels().size(),
                           " channels, ", inputs.size(), " given"));
    format::WriterOptions options;
    options.dims = tmpl.dims(0);
    options.spacing_mm = tmpl.spacing_mm(0);
    options.origin_mm = tmpl.origin_mm(0);
    options.brick_edge = int(brick_edge.value_or(tmpl.brick_edge()));
    options.zstd_level = zstd_level;
    options.threads = threads;
    options.label_table = tmpl.label_table();
    const auto read_start = Clock::now();
    std::vector<NrrdVolume> volumes;
    std::uint64_t raw_bytes = 0;
    for (std::size_t c = 0; c < inputs.size(); ++c) {
      format::ChannelSpec spec = tmpl.channels()[c];
      if (spec.type == format::ChannelType::kUint8 && !options.label_table.empty() &&
          spec.name == "labels")
        spec.type = format::ChannelType::kUint16;  // passed as uint16, narrowed by the Writer
      options.channels.push_back(spec);
      volumes.push_back(read_nrrd(inputs[c]));
      if (volumes.back().dims != options.dims)
        throw InputError(cat(inputs[c], ": dims differ from ", template_path));
      raw_bytes += volumes.back().data.size();
    }
    const std::int64_t nz = options.dims[2];
    options.dims[2] *= repeat;
    raw_bytes *= std::uint64_t(repeat);
    const double read_s = since(read_start);

    const std::size_t plane = std::size_t(options.dims[0]) * std::size_t(options.dims[1]);
    std::vector<std::uint16_t> widened(plane);
    // Profiling the write alone: `perf record --control=fifo:CTL -D -1 ...` with
    // VISPACK_PERF_CTL=CTL starts the profile here.
    if (const char* ctl = std::getenv("VISPACK_PERF_CTL")) {
      if (std::FILE* f = std::fopen(ctl, "w")) {
        std::fputs("enable\n", f);
        std::fclose(f);
      }
    }
    const auto cpu0 = cpu_seconds();
    const auto start = Clock::now();
    format::Writer writer(out_path, options);
    for (std::int64_t z = 0; z < options.dims[2]; ++z) {
      std::vector<const void*> slices;
      for (std::size_t c = 0; c < volumes.size(); ++c) {
        const NrrdVolume& v = volumes[c];
        const std::size_t voxel = std::size_t(v.components) * nrrd_type_size(v.type);
        const std::uint8_t* slice = v.data.data() + std::size_t(z % nz) * plane * voxel;
        if (options.channels[c].type == format::ChannelType::kUint16 && voxel == 1) {
          for (std::size_t i = 0; i < plane; ++i)
            widened[i] = slice[i];
          slices.push_back(widened.data());
        } else {
          slices.push_back(slice);
        }
      }
      writer.append_slice(slices);
    }
    writer.finish();
    const double write_s = since(start);
    const auto cpu1 = cpu_seconds();
    const double user_s = cpu1.first - cpu0.first, sys_s = cpu1.second - cpu0.second;
    std::printf(
        "{\"raw_bytes\": %llu, \"read_s\": %.4f, \"write_s\": %.4f, \"write_cpu_s\": %.4f, "
        "\"write_user_s\": %.4f, \"write_sys_s\": %.4f, \"threads\": %d, \"zstd_level\": %d, "
        "\"repeat\": %d, \"out_bytes\": %llu}\n",
        static_cast<unsigned long long>(raw_bytes), read_s, write_s, user_s + sys_s, user_s, sys_s,
        threads, zstd_level, repeat,
        static_cast<unsigned long long>(format::Reader::open(out_path).file_size()));
    return 0;
  });
}

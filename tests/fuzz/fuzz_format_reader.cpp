// Fuzz target: the packed-file reader (header, metadata, index, brick decode, verify).
// Any input must give either a valid Reader or a FormatError/IoError — never a crash, a hang or
// an out-of-bounds read (run under ASan+UBSan).
#include <cstring>
#include <vector>

#include "fuzz_target.h"
#include "scratch.h"
#include "vispack/common/error.h"
#include "vispack/format/reader.h"
#include "vispack/format/writer.h"

using namespace vispack::format;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  std::string path = vispack_fuzz_scratch_dir() + "/input.vpk";
  vispack_fuzz_write(path, data, size);
  ReaderLimits limits;
  limits.max_level_voxels = std::uint64_t(1) << 24;  // keep decodes small while fuzzing
  limits.max_index_entries = 1 << 16;
  try {
    Reader reader = Reader::open(path, limits);
    (void)reader.metadata().dump();
    std::vector<std::uint8_t> buffer;
    std::size_t decoded = 0;
    for (const BrickInfo& brick : reader.bricks()) {
      if (decoded++ >= 64) break;
      buffer.resize(reader.brick_bytes(brick.channel));
      try {
        reader.decode_brick(brick, buffer.data(), buffer.size(), true);
        (void)reader.brick_labels(brick);
      } catch (const vispack::Error&) {
      }
    }
    // A small region from each channel at the coarsest level.
    int level = reader.level_count() - 1;
    auto dims = reader.dims(level);
    for (int c = 0; c < int(reader.channels().size()); ++c) {
      std::int64_t nx = std::min<std::int64_t>(dims[0], 4), ny = std::min<std::int64_t>(dims[1], 4),
                   nz = std::min<std::int64_t>(dims[2], 4);
      buffer.resize(std::size_t(nx * ny * nz) * channel_type_bytes(reader.channels()[c].type));
      try {
        reader.read_region(c, level, 0, 0, 0, nx, ny, nz, buffer.data());
      } catch (const vispack::Error&) {
      }
    }
    (void)reader.verify(true, 1);
  } catch (const vispack::Error&) {
  } catch (const std::out_of_range&) {
  } catch (const std::invalid_argument&) {
  }
  return 0;
}

namespace {

// A small volume with every channel type, uniform bricks and a partial brick row.
void write_seed(const std::string& path, std::array<std::int64_t, 3> dims, int brick_edge,
                int zstd_level, bool with_labels) {
  WriterOptions options;
  options.dims = dims;
  options.spacing_mm = {0.33, 0.33, 1.0};
  options.brick_edge = brick_edge;
  options.zstd_level = zstd_level > 0 ? zstd_level : 1;
  options.compress = zstd_level > 0;
  options.threads = 1;
  options.channels = {{"rgba", ChannelType::kRgba8}, {"ct", ChannelType::kInt16}};
  if (with_labels) {
    options.channels.push_back({"labels", ChannelType::kUint16});
    options.label_table = {{1, "skin", {200, 150, 120}}, {3, "bone", {240, 240, 230}}};
  }
  Writer writer(path, options);
  std::size_t n = std::size_t(dims[0] * dims[1]);
  std::vector<std::uint8_t> rgba(n * 4);
  std::vector<std::int16_t> ct(n);
  std::vector<std::uint16_t> labels(n);
  for (std::int64_t z = 0; z < dims[2]; ++z) {
    for (std::size_t i = 0; i < n; ++i) {
      std::int64_t x = std::int64_t(i) % dims[0], y = std::int64_t(i) / dims[0];
      bool body = (x - dims[0] / 2) * (x - dims[0] / 2) + (y - dims[1] / 2) * (y - dims[1] / 2) <
                  dims[0] * dims[0] / 9;
      rgba[4 * i + 0] = body ? std::uint8_t(180 + (x + z) % 40) : 40;
      rgba[4 * i + 1] = body ? 90 : 60;
      rgba[4 * i + 2] = body ? 80 : 200;
      rgba[4 * i + 3] = body ? 255 : 0;
      ct[i] = body ? std::int16_t(40 + (x * 7 + y * 3 + z) % 300) : -1000;
      labels[i] = body ? (x < dims[0] / 2 ? 1 : 3) : 0;
    }
    std::vector<const void*> slices = {rgba.data(), ct.data()};
    if (with_labels) slices.push_back(labels.data());
    writer.append_slice(slices);
  }
  writer.finish();
}

}  // namespace

void vispack_fuzz_write_seeds(const std::string& dir) {
  write_seed(dir + "/small-zstd.vpk", {20, 12, 9}, 8, 3, true);
  write_seed(dir + "/small-raw.vpk", {9, 17, 5}, 8, 0, true);
  write_seed(dir + "/one-voxel.vpk", {1, 1, 1}, 8, 1, false);
  write_seed(dir + "/edge16.vpk", {17, 16, 3}, 16, 9, true);
}

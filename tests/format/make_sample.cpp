// format_make_sample OUT.vpk [--dims X,Y,Z] [--edge E] [--labels N] [--empty-label-table] [--raw]
// Writes a small deterministic packed volume (default 40 x 30 x 20 voxels, rgba + ct + labels,
// brick edge 16) for tests that need a file without the pipeline (the install/consumer test, the
// OME-Zarr export tests). --labels N relabels the body with IDs 1..N (N > 255 stores uint16);
// --empty-label-table writes the label channel (uint16) with no label table; --raw stores every
// non-uniform brick uncompressed.
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <string>

#include "format_test_util.h"

namespace {

using namespace vispack::format::testing;

bool parse_dims(const char* text, Dims* d) {
  long long x = 0, y = 0, z = 0;
  char tail = 0;
  if (std::sscanf(text, "%lld,%lld,%lld%c", &x, &y, &z, &tail) != 3) return false;
  if (x < 1 || y < 1 || z < 1) return false;
  *d = {x, y, z};
  return true;
}

// IDs 1..n over the body (0 outside stays 0), varied enough that a brick holds many.
void relabel(Volume& v, std::uint32_t n) {
  v.label_table.clear();
  for (std::uint32_t id = 1; id <= n; ++id) {
    v.label_table.push_back({id,
                             "structure " + std::to_string(id),
                             {std::uint8_t(id * 37), std::uint8_t(id * 11), std::uint8_t(id)}});
  }
  const Dims d = v.dims;
  for (std::int64_t z = 0; z < d[2]; ++z)
    for (std::int64_t y = 0; y < d[1]; ++y)
      for (std::int64_t x = 0; x < d[0]; ++x) {
        const std::size_t i = std::size_t((z * d[1] + y) * d[0] + x);
        std::uint16_t label;
        std::memcpy(&label, &v.data[2][2 * i], 2);
        if (label == 0) continue;
        label = std::uint16_t(1 + (x / 3 + (y / 3) * 5 + (z / 2) * 11) % n);
        std::memcpy(&v.data[2][2 * i], &label, 2);
      }
}

}  // namespace

int main(int argc, char** argv) {
  const char* usage =
      "usage: format_make_sample OUT.vpk [--dims X,Y,Z] [--edge E] [--labels N] "
      "[--empty-label-table] [--raw]\n";
  if (argc < 2 || argv[1][0] == '-') {
    std::fprintf(stderr, "%s", usage);
    return 2;
  }
  Dims dims{40, 30, 20};
  int edge = 16;
  long labels = 0;
  bool empty_table = false, raw = false;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    const bool has_value = i + 1 < argc;
    if (a == "--dims" && has_value && parse_dims(argv[i + 1], &dims)) {
      ++i;
    } else if (a == "--edge" && has_value) {
      edge = std::atoi(argv[++i]);
    } else if (a == "--labels" && has_value) {
      labels = std::atol(argv[++i]);
      if (labels < 1 || labels > 65535) {
        std::fprintf(stderr, "format_make_sample: --labels must be in [1, 65535]\n");
        return 2;
      }
    } else if (a == "--empty-label-table") {
      empty_table = true;
    } else if (a == "--raw") {
      raw = true;
    } else {
      std::fprintf(stderr, "format_make_sample: bad argument \"%s\"\n%s", a.c_str(), usage);
      return 2;
    }
  }
  try {
    Volume v = make_volume(dims, 5);
    if (labels > 0) relabel(v, std::uint32_t(labels));
    if (empty_table) v.label_table.clear();
    vispack::format::WriterOptions options = options_for(v, edge);
    options.compress = !raw;
    write(argv[1], v, options);
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "format_make_sample: error: %s\n", e.what());
    return 1;
  }
}

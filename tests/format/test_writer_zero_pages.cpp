// The Writer's level-0 slab leaves pages untouched where slices are zero
// (common/zero_paged_buffer.h): a Writer whose slab is reused over slabs whose zero regions move
// gives the volume back bit for bit.
#include <gtest/gtest.h>

#include <cstring>

#include "format_test_util.h"

using namespace vispack::format;
using namespace vispack::format::testing;

// Slices whose colour and labels are zero outside a band of rows that moves from slice to slice,
// wide enough that whole pages of a slice are zero in one slab and not in the next (the slab is
// reused): every level reads back as written, uint8 labels (narrowed into the slab) and uint16
// (copied), on one thread and three.
TEST(ZeroPages, SlabReusedOverMovingZeroRegionsGivesTheVolumeBack) {
  for (std::uint32_t max_label : {40u, 300u}) {
    Volume v = make_volume({256, 64, 29}, 9, max_label);  // 4 slabs of 8 (a short last one)
    const std::size_t plane = 256 * 64;
    for (std::int64_t z = 0; z < v.dims[2]; ++z) {
      const std::int64_t band0 = (z * 13) % 64, band1 = band0 + 9 + z % 17;
      for (std::int64_t y = 0; y < 64; ++y) {
        if (y >= band0 && y < band1) continue;
        const std::size_t i = std::size_t(z) * plane + std::size_t(y) * 256;
        std::memset(&v.data[0][4 * i], 0, 4 * 256);  // colour: zero outside the band
        std::memset(&v.data[2][2 * i], 0, 2 * 256);  // labels: 0
      }
    }
    const std::string reference = temp_path("reference.vpk");
    write(reference, v, options_for(v, 8, 1));
    for (int threads : {1, 3}) {
      const std::string path = temp_path("zero_pages.vpk");
      write(path, v, options_for(v, 8, threads));
      Reader r = Reader::open(path);
      for (std::size_t c = 0; c < v.channels.size(); ++c) {
        const auto expected = to_stored(v.data[c], v.channels[c].type, r.channels()[c].type);
        EXPECT_TRUE(r.read_level(int(c), 0, 2) == expected)
            << "channel " << c << ", labels up to " << max_label << ", threads " << threads;
      }
      EXPECT_TRUE(read_bytes(path) == read_bytes(reference)) << "threads " << threads;
    }
  }
}

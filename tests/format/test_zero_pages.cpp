// The Writer's level-0 slab leaves pages untouched where slices are zero
// (format/src/zero_paged_buffer.h): zeros written over data still read back as zeros, pages
// that only ever got zeros cost no memory, and a Writer whose slab is reused over slabs whose
// zero regions move gives the volume back bit for bit.
#include <gtest/gtest.h>

#include <sys/mman.h>

#include <cstring>
#include <random>
#include <vector>

#include "../../format/src/zero_paged_buffer.h"  // internal to the writer: tested directly
#include "format_test_util.h"

using namespace vispack::format;
using namespace vispack::format::testing;
using vispack::format::detail::ZeroPagedBuffer;

namespace {

// How many of the buffer's pages are resident (mincore): untouched anonymous pages are not.
std::size_t resident_pages(const ZeroPagedBuffer& b) {
  const std::size_t page = ZeroPagedBuffer::page_size();
  const std::size_t pages = (b.size() + page - 1) / page;
  std::vector<unsigned char> in(pages);
  EXPECT_EQ(::mincore(const_cast<std::uint8_t*>(b.data()), pages * page, in.data()), 0);
  std::size_t n = 0;
  for (unsigned char c : in)
    n += c & 1;
  return n;
}

}  // namespace

TEST(ZeroPages, ZerosOverDataReadBackAsZerosAndUntouchedPagesStayFree) {
  const std::size_t page = ZeroPagedBuffer::page_size();
  const std::size_t size = 16 * page + 100;  // a partial last page
  ZeroPagedBuffer b(size);
  std::vector<std::uint8_t> model(size, 0), zeros(size, 0), data(size);
  std::mt19937 rng(5);
  for (auto& v : data)
    v = std::uint8_t(1 + rng() % 255);
  // Zeros over a fresh buffer: nothing touched.
  b.write(0, zeros.data(), size);
  EXPECT_LE(resident_pages(b), 1u) << "only the partial last page may be written";
  // Data at an unaligned range, then zeros over part of it (whole pages, partial pages), then
  // data again; after each step the buffer equals a plain copy.
  struct Step {
    std::size_t at, n;
    bool zero;
  };
  for (const Step& s : {Step{page / 2, 5 * page, false}, Step{0, 3 * page + 7, true},
                        Step{2 * page, 10 * page + 100, false}, Step{page, 12 * page, true},
                        Step{0, size, true}, Step{4 * page - 1, 2, false}}) {
    const std::uint8_t* src = s.zero ? zeros.data() : data.data() + s.at;
    b.write(s.at, src, s.n);
    std::memcpy(model.data() + s.at, src, s.n);
    ASSERT_EQ(std::memcmp(b.data(), model.data(), size), 0)
        << "after writing " << s.n << " " << (s.zero ? "zero" : "data") << " bytes at " << s.at;
  }
  // Narrowed uint16 IDs, zero and not, over data.
  std::vector<std::uint16_t> ids(8 * page, 0);
  for (std::size_t i = 3 * page; i < 4 * page + 9; ++i)
    ids[i] = std::uint16_t(1 + i % 200);
  b.write_narrowed(page, ids.data(), ids.size());
  for (std::size_t i = 0; i < ids.size(); ++i)
    model[page + i] = std::uint8_t(ids[i]);
  ASSERT_EQ(std::memcmp(b.data(), model.data(), size), 0) << "after write_narrowed";
  // Written through data() and declared: zeros written afterwards are not skipped.
  std::memset(b.data() + 9 * page, 0xab, page);
  b.mark_written(9 * page, page);
  b.write(9 * page, zeros.data(), page);
  std::memset(model.data() + 9 * page, 0, page);
  ASSERT_EQ(std::memcmp(b.data(), model.data(), size), 0) << "after mark_written";
}

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

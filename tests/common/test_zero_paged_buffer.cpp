// ZeroPagedBuffer (common/zero_paged_buffer.h): zeros written over data still read back as
// zeros, and pages that only ever got zeros cost no memory.
#include <gtest/gtest.h>

#include <cstring>
#include <random>
#include <vector>

#include "test_support.h"
#include "vispack/common/zero_paged_buffer.h"

using vispack::ZeroPagedBuffer;

namespace {

// How many of the buffer's pages are resident: untouched anonymous pages are not.
std::size_t resident_pages(const ZeroPagedBuffer& b) {
  return vispack::test::resident_pages(b.data(), b.size());
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
}

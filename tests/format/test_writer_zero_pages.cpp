// The Writer's level-0 slab leaves pages untouched where slices are zero
// (common/zero_paged_buffer.h): a Writer whose slab is reused over slabs whose zero regions move
// gives the volume back bit for bit; the slab's zero pages are never read (by the Writer or by a
// shard's encode_level0_slab); a merge's payloads copied from their file, and the zstd frames a
// shard's level-1 slices travel in.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/resource.h>
#include <unistd.h>

#include <cstring>
#include <functional>
#include <memory>

#include "format_test_util.h"
#include "test_support.h"
#include "vispack/common/error.h"
#include "vispack/common/zero_paged_buffer.h"

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

namespace {

// A volume whose colour and labels are zero outside a box of [x0, x1) x [y0, y1) (all slices),
// as the pack clears them outside the body: whole rows above and below the box are zero pages.
Volume boxed_volume(Dims d, std::int64_t x0, std::int64_t x1, std::int64_t y0, std::int64_t y1) {
  Volume v = make_volume(d, 5, 40);
  for (std::int64_t z = 0; z < d[2]; ++z)
    for (std::int64_t y = 0; y < d[1]; ++y)
      for (std::int64_t x = 0; x < d[0]; ++x)
        if (x < x0 || x >= x1 || y < y0 || y >= y1) {
          const std::size_t i = std::size_t((z * d[1] + y) * d[0] + x);
          std::memset(&v.data[0][4 * i], 0, 4);
          std::memset(&v.data[2][2 * i], 0, 2);
        }
  return v;
}

// Resident pages of a buffer: untouched anonymous pages are not.
std::size_t resident_pages(const vispack::ZeroPagedBuffer& b) {
  return vispack::test::resident_pages(b.data(), b.size());
}

long minor_faults() {
  struct rusage u {};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_minflt;
}

}  // namespace

// A pack shard's slab lies in ZeroPagedBuffers: encoding it with them (the bricks' gather and the
// level-1 reduction skip the pages they know to be zero) gives the bricks and level-1 slices of
// the plain encoding, byte for byte, and faults none of those pages in (on a kernel without a
// shared zero page each such read allocated and cleared a page; reading them costs a fault
// anywhere). Two brick edges (a row of a brick within one page, and a brick row spanning pages)
// and one and two threads.
TEST(ZeroPages, SlabEncodedFromZeroPagedBuffersLeavesZeroPagesUntouched) {
  const Dims dims{1024, 64, 16};
  const Volume v = boxed_volume(dims, 300, 700, 20, 44);
  const std::size_t plane = std::size_t(dims[0] * dims[1]);
  for (int edge : {8, 16})
    for (int threads : {1, 2}) {
      const WriterOptions o = options_for(v, edge, threads);
      ASSERT_EQ(stored_channels_for(o)[2].type, ChannelType::kUint8);
      for (std::int64_t bz = 0; bz < level0_slab_count(o); ++bz) {
        const std::size_t z0 = std::size_t(bz * edge), nz = std::size_t(edge);
        vispack::ZeroPagedBuffer rgba(plane * 4 * nz), ct(plane * 2 * nz), labels(plane * nz);
        rgba.write(0, v.data[0].data() + plane * 4 * z0, plane * 4 * nz);
        ct.write(0, v.data[1].data() + plane * 2 * z0, plane * 2 * nz);
        labels.write_narrowed(
            0, reinterpret_cast<const std::uint16_t*>(v.data[2].data()) + plane * z0, plane * nz);
        const std::size_t rgba_before = resident_pages(rgba),
                          labels_before = resident_pages(labels);
        ASSERT_LT(rgba_before * 2, rgba.size() / vispack::ZeroPagedBuffer::page_size())
            << "the test needs most colour pages zero";
        std::vector<std::vector<std::uint8_t>> level1(3);
        std::vector<int> next_k(3, 0);
        auto sink = [&](std::size_t c, int k, const std::uint8_t* slice, std::size_t bytes) {
          EXPECT_EQ(k, next_k[c]++) << "channel " << c;
          level1[c].insert(level1[c].end(), slice, slice + bytes);
        };
        const std::vector<EncodedBrick> bricks =
            encode_level0_slab(o, bz, {rgba.data(), ct.data(), labels.data()}, sink,
                               SlabLabels::kStored, {&rgba, &ct, &labels});
        EXPECT_EQ(resident_pages(rgba), rgba_before) << "edge " << edge << ", slab " << bz;
        EXPECT_EQ(resident_pages(labels), labels_before) << "edge " << edge << ", slab " << bz;

        // The plain encoding from ordinary memory (labels narrowed as stored).
        std::vector<std::uint8_t> narrowed(plane * nz);
        for (std::size_t i = 0; i < narrowed.size(); ++i)
          narrowed[i] = v.data[2][2 * (plane * z0 + i)];
        std::vector<std::vector<std::uint8_t>> expected_level1;
        const std::vector<EncodedBrick> expected = encode_level0_slab(
            o, bz,
            {v.data[0].data() + plane * 4 * z0, v.data[1].data() + plane * 2 * z0, narrowed.data()},
            &expected_level1, SlabLabels::kStored);
        ASSERT_EQ(bricks.size(), expected.size());
        for (std::size_t i = 0; i < bricks.size(); ++i) {
          EXPECT_EQ(bricks[i].codec, expected[i].codec) << "brick " << i;
          EXPECT_EQ(bricks[i].min, expected[i].min) << "brick " << i;
          EXPECT_EQ(bricks[i].max, expected[i].max) << "brick " << i;
          EXPECT_EQ(bricks[i].checksum, expected[i].checksum) << "brick " << i;
          EXPECT_TRUE(bricks[i].payload == expected[i].payload) << "brick " << i;
          EXPECT_EQ(bricks[i].labels, expected[i].labels) << "brick " << i;
        }
        EXPECT_TRUE(level1 == expected_level1) << "edge " << edge << ", slab " << bz;
      }
    }
}

// The Writer's own level-0 slab: its gather and its level-1 reduction never read the slab's zero
// pages either. Counted in the process's minor page faults while a volume whose colour and
// labels are zero outside a small box is written: the slab's colour and label pages outside the
// box (about 9,000 here) would each fault once if read; everything the Writer touches for
// certain (the CT channel's part of the slab, never zero; the box's pages) is under 6,000.
// Measured: 7,000-8,000 faults in all, 15,658 when either the gather or the reduction read the
// zero pages; the bound is three quarters of the slab's pages (10,752). Skipped under
// AddressSanitizer, whose shadow memory faults pages of its own.
TEST(ZeroPages, WriterNeverReadsTheZeroPagesOfItsSlab) {
#if defined(__SANITIZE_ADDRESS__)
  GTEST_SKIP() << "page faults include AddressSanitizer's shadow memory";
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
  GTEST_SKIP() << "page faults include AddressSanitizer's shadow memory";
#endif
#endif
  const Dims dims{2048, 128, 64};
  const Volume v = boxed_volume(dims, 900, 1100, 56, 72);
  WriterOptions o = options_for(v, 32, 1);
  const std::string path = temp_path("boxed.vpk");
  const std::size_t page = vispack::ZeroPagedBuffer::page_size();
  const std::size_t slab_pages = std::size_t(dims[0] * dims[1] * 32) * (4 + 2 + 1) / page;
  const long before = minor_faults();
  write(path, v, o);
  const long faults = minor_faults() - before;
  Reader r = Reader::open(path);
  for (std::size_t c = 0; c < v.channels.size(); ++c)
    EXPECT_TRUE(r.read_level(int(c), 0, 1) ==
                to_stored(v.data[c], v.channels[c].type, r.channels()[c].type))
        << "channel " << c;
  EXPECT_LT(faults, long(slab_pages) * 3 / 4)
      << faults << " minor faults for a slab of " << slab_pages << " pages";
}

// The merge hands the Writer its shards' bricks with their stored bytes left in their files
// (PayloadFile): the same file as with the bytes in memory, and as append_slice.
TEST(Writer, ProvidedPayloadsCopiedFromAFileGiveTheSameBytes) {
  const Volume v = make_volume({70, 30, 40}, 3, 40);
  const WriterOptions o = options_for(v, 16, 2);
  const std::string whole = temp_path("whole-pf.vpk"), merged = temp_path("merged-pf.vpk");
  write(whole, v, o);
  const std::string payloads = temp_path("payloads.bin");
  const std::size_t plane = 70 * 30;
  {
    Writer w(merged, o);
    std::vector<int> fds;
    std::vector<std::unique_ptr<PayloadFile>> files;
    for (std::int64_t bz = 0; bz < level0_slab_count(o); ++bz) {
      std::vector<const void*> slab;
      for (std::size_t c = 0; c < 3; ++c)
        slab.push_back(v.data[c].data() + plane * std::size_t(bz * 16) * (c == 0 ? 4 : 2));
      std::vector<std::vector<std::uint8_t>> level1;
      std::vector<EncodedBrick> bricks = encode_level0_slab(o, bz, slab, &level1);
      // The payloads into a file of their own, after some bytes that are not theirs; the bricks
      // keep only where they are.
      const std::string name = payloads + std::to_string(bz);
      std::vector<std::uint8_t> bytes(13, 0xAB);
      for (auto& b : bricks) {
        b.file_offset = bytes.size();
        b.file_bytes = b.payload.size();
        bytes.insert(bytes.end(), b.payload.begin(), b.payload.end());
        b.payload.clear();
      }
      write_bytes(name, bytes);
      fds.push_back(::open(name.c_str(), O_RDONLY));
      ASSERT_GE(fds.back(), 0);
      files.push_back(std::make_unique<PayloadFile>(PayloadFile{fds.back(), name}));
      w.provide_level0_slab(bz, std::move(bricks), files.back().get());
      const std::size_t n1 = std::size_t((std::min<std::int64_t>(16, 40 - bz * 16) + 1) / 2);
      append_level1_slices(w, level1, n1);
    }
    w.finish();
    for (int fd : fds)
      ::close(fd);
  }
  EXPECT_TRUE(read_bytes(whole) == read_bytes(merged));
}

// ZstdFrameWriter fed in pieces gives one frame that decompress_bytes and ZstdFrameReader (read
// in other pieces) decode to the same bytes; the reader refuses a truncated frame, a frame with
// more bytes than asked, and trailing bytes, naming what it reads.
TEST(ZstdFrames, PiecewiseFramesRoundTripAndBadFramesAreNamed) {
  std::vector<std::uint8_t> data(300000);
  for (std::size_t i = 0; i < data.size(); ++i)
    data[i] = std::uint8_t((i / 700) * 31 + (i % 7 == 0 ? i : 0));
  for (std::size_t piece : {std::size_t(1000), std::size_t(65536), data.size()}) {
    ZstdFrameWriter w(data.size(), 1);
    for (std::size_t at = 0; at < data.size(); at += piece)
      w.write(data.data() + at, std::min(piece, data.size() - at));
    const std::vector<std::uint8_t> frame = w.finish();
    std::vector<std::uint8_t> whole(data.size());
    decompress_bytes(frame.data(), frame.size(), whole.data(), whole.size(), "frame");
    EXPECT_TRUE(whole == data) << "pieces of " << piece;
    ZstdFrameReader r(frame.data(), frame.size(), "frame");
    std::vector<std::uint8_t> back(data.size());
    for (std::size_t at = 0; at < back.size(); at += 4099)
      r.read(back.data() + at, std::min<std::size_t>(4099, back.size() - at));
    r.finish();
    EXPECT_TRUE(back == data) << "pieces of " << piece;
  }
  ZstdFrameWriter w(data.size(), 1);
  w.write(data.data(), data.size());
  std::vector<std::uint8_t> frame = w.finish();
  auto expect_error = [](const std::function<void()>& f, const std::string& what) {
    try {
      f();
      ADD_FAILURE() << "no error: " << what;
    } catch (const vispack::FormatError& e) {
      EXPECT_NE(std::string(e.what()).find("slab.bin: level-1"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  };
  std::vector<std::uint8_t> out(data.size() + 1);
  expect_error(
      [&] {
        ZstdFrameReader r(frame.data(), frame.size() - 5, "slab.bin: level-1");
        r.read(out.data(), data.size());
      },
      "truncated");
  expect_error(
      [&] {
        ZstdFrameReader r(frame.data(), frame.size(), "slab.bin: level-1");
        r.read(out.data(), data.size() - 1);
        r.finish();
      },
      "more bytes");
  expect_error(
      [&] {
        ZstdFrameReader r(frame.data(), frame.size(), "slab.bin: level-1");
        r.read(out.data(), data.size() + 1);
      },
      "ends early");
  frame.push_back(0);
  expect_error(
      [&] {
        ZstdFrameReader r(frame.data(), frame.size(), "slab.bin: level-1");
        r.read(out.data(), data.size());
        r.finish();
      },
      "trailing bytes");
  EXPECT_THROW(ZstdFrameWriter(10, 1).write(data.data(), 11), std::invalid_argument);
  EXPECT_THROW(ZstdFrameWriter(10, 1).finish(), std::invalid_argument);
}

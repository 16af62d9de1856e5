// Round trips: every channel type, every level, awkward dims; random access; uniform bricks;
// the reduction rules; byte-reproducible output.
#include <gtest/gtest.h>

#include <sys/resource.h>

#include <csignal>
#include <cstdlib>
#include <fstream>
#include <set>
#include <string>

#include "format_test_util.h"
#include "vispack/common/hash.h"

using namespace vispack::format;
using namespace vispack::format::testing;

namespace {

struct Case {
  Dims dims;
  int edge;
  std::uint32_t max_label;  // > 255 gives a uint16 label channel
};

void check_all_levels(const std::string& path, const Volume& v) {
  Reader r = Reader::open(path);
  ASSERT_EQ(r.channels().size(), v.channels.size());
  EXPECT_EQ(r.level_count(), Writer::level_count_for(v.dims, r.brick_edge()));
  const LevelInfo& last = r.level(r.level_count() - 1);
  for (int a = 0; a < 3; ++a)
    EXPECT_LE(last.dims[a], r.brick_edge()) << "top level must fit one brick";
  for (std::size_t c = 0; c < v.channels.size(); ++c) {
    const ChannelType stored = r.channels()[c].type;
    std::vector<std::uint8_t> expected = to_stored(v.data[c], v.channels[c].type, stored);
    Dims d = v.dims;
    for (int l = 0; l < r.level_count(); ++l) {
      ASSERT_EQ(r.dims(l), d) << "level " << l;
      std::vector<std::uint8_t> got = r.read_level(int(c), l, 2);
      ASSERT_EQ(got.size(), expected.size());
      ASSERT_TRUE(got == expected) << "channel " << r.channels()[c].name << " level " << l
                                   << " dims " << d[0] << "x" << d[1] << "x" << d[2];
      Dims next{};
      expected = reference_downsample(expected, d, stored, &next);
      d = next;
    }
  }
  VerifyResult vr = r.verify(true);
  EXPECT_TRUE(vr.ok) << vr.message;
}

class RoundTrip : public ::testing::TestWithParam<Case> {};

TEST_P(RoundTrip, EveryChannelEveryLevelBitExact) {
  const Case& c = GetParam();
  Volume v = make_volume(c.dims, 7, c.max_label);
  std::string path = temp_path("rt.vpk");
  write(path, v, options_for(v, c.edge));
  Reader r = Reader::open(path);
  EXPECT_EQ(r.channels()[2].type, c.max_label > 255 ? ChannelType::kUint16 : ChannelType::kUint8);
  check_all_levels(path, v);
}

INSTANTIATE_TEST_SUITE_P(
    AwkwardDims, RoundTrip,
    ::testing::Values(Case{{1, 1, 1}, 8, 40},        // a single voxel
                      Case{{1, 37, 1}, 8, 40},       // a line along y
                      Case{{65, 33, 130}, 64, 40},   // one over a brick multiple in x, default edge
                      Case{{65, 33, 130}, 16, 300},  // same with uint16 labels, many levels
                      Case{{7, 11, 13}, 4, 40},      // primes, smallest edge
                      Case{{31, 17, 5}, 8, 300},     // primes, one brick row (z < edge)
                      Case{{40, 24, 8}, 8, 40},      // exactly one brick row
                      Case{{17, 9, 33}, 8, 40}));    // one voxel over a brick multiple on x, z

TEST(RoundTrip, UncompressedBricksAreZeroCopyViews) {
  Volume v = make_volume({20, 12, 10}, 3);
  std::string path = temp_path("raw.vpk");
  WriterOptions o = options_for(v, 8);
  o.compress = false;
  write(path, v, o);
  Reader r = Reader::open(path);
  int raw = 0;
  for (const BrickInfo& b : r.bricks()) {
    ASSERT_NE(b.codec, Codec::kZstd);
    if (b.codec != Codec::kRaw) continue;
    ++raw;
    auto view = r.raw_brick_view(b);
    ASSERT_TRUE(view.has_value());
    EXPECT_EQ(reinterpret_cast<std::uintptr_t>(view->data) % kPayloadAlignment, 0u)
        << "payloads are page-aligned";
    std::vector<std::uint8_t> decoded(r.brick_bytes(b.channel));
    r.decode_brick(b, decoded.data(), decoded.size(), true);
    EXPECT_EQ(0, std::memcmp(decoded.data(), view->data, decoded.size()));
  }
  EXPECT_GT(raw, 0);
  check_all_levels(path, v);
}

TEST(RandomAccess, RegionsAgreeWithFullReads) {
  Volume v = make_volume({45, 38, 29}, 11, 300);
  std::string path = temp_path("ra.vpk");
  write(path, v, options_for(v, 8));
  Reader r = Reader::open(path);
  std::mt19937 rng(5);
  for (int c = 0; c < 3; ++c) {
    for (int l = 0; l < r.level_count(); ++l) {
      const Dims d = r.dims(l);
      const std::size_t vb = channel_type_bytes(r.channels()[std::size_t(c)].type);
      std::vector<std::uint8_t> full = r.read_level(c, l);
      for (int trial = 0; trial < 20; ++trial) {
        Dims o{}, n{};
        for (int a = 0; a < 3; ++a) {
          o[a] = std::uniform_int_distribution<std::int64_t>(0, d[a] - 1)(rng);
          n[a] = std::uniform_int_distribution<std::int64_t>(1, d[a] - o[a])(rng);
        }
        std::vector<std::uint8_t> box(std::size_t(n[0] * n[1] * n[2]) * vb);
        r.read_region(c, l, o[0], o[1], o[2], n[0], n[1], n[2], box.data());
        for (std::int64_t z = 0; z < n[2]; ++z)
          for (std::int64_t y = 0; y < n[1]; ++y)
            ASSERT_EQ(0, std::memcmp(
                             &box[std::size_t((z * n[1] + y) * n[0]) * vb],
                             &full[std::size_t(((o[2] + z) * d[1] + o[1] + y) * d[0] + o[0]) * vb],
                             std::size_t(n[0]) * vb))
                << "channel " << c << " level " << l << " trial " << trial;
      }
    }
  }
  // Out-of-range boxes are refused, not read.
  std::vector<std::uint8_t> buf(64);
  EXPECT_THROW(r.read_region(1, 0, 44, 0, 0, 2, 1, 1, buf.data()), std::out_of_range);
  EXPECT_THROW(r.read_region(1, r.level_count(), 0, 0, 0, 1, 1, 1, buf.data()), std::out_of_range);
  EXPECT_THROW(r.read_region("nope", 0, 0, 0, 0, 1, 1, 1, buf.data()), std::out_of_range);
}

TEST(RandomAccess, DecodedBricksReplicatePadding) {
  Volume v = make_volume({10, 9, 11}, 2);
  std::string path = temp_path("pad.vpk");
  write(path, v, options_for(v, 8));
  Reader r = Reader::open(path);
  const BrickInfo& b = r.brick(1, 0, 1, 1, 1);  // covers x 8..9, y 8, z 8..10 of level 0
  std::vector<std::int16_t> brick(512);
  r.decode_brick(b, brick.data(), brick.size() * 2);
  auto at = [&](std::int64_t x, std::int64_t y, std::int64_t z) {
    std::int16_t hu;
    std::memcpy(&hu, &v.data[1][std::size_t((z * 9 + y) * 10 + x) * 2], 2);
    return hu;
  };
  for (int z = 0; z < 8; ++z)
    for (int y = 0; y < 8; ++y)
      for (int x = 0; x < 8; ++x)
        ASSERT_EQ(brick[std::size_t((z * 8 + y) * 8 + x)],
                  at(8 + std::min(x, 1), 8, 8 + std::min(z, 2)));
}

TEST(UniformBricks, StoreNoPayloadAndReadBack) {
  Volume v = make_volume({24, 16, 16}, 4);
  // Make the whole CT channel air and every label 0 except one voxel.
  for (std::size_t i = 0; i < v.data[1].size() / 2; ++i) {
    std::int16_t hu = -1000;
    std::memcpy(&v.data[1][2 * i], &hu, 2);
    v.data[2][2 * i] = v.data[2][2 * i + 1] = 0;
  }
  v.data[2][2 * (5 + 24 * 3)] = 7;  // label 7 at (5, 3, 0)
  std::string path = temp_path("uniform.vpk");
  write(path, v, options_for(v, 8));
  Reader r = Reader::open(path);
  std::uint64_t ct_stored = 0;
  for (const BrickInfo& b : r.bricks()) {
    if (b.channel != 1) continue;
    EXPECT_EQ(b.codec, Codec::kUniform);
    EXPECT_EQ(b.min[0], -1000);
    ct_stored += b.stored_size;
  }
  EXPECT_EQ(ct_stored, 0u) << "uniform bricks cost only their index entry";
  const BrickInfo& with7 = r.brick(2, 0, 0, 0, 0);
  EXPECT_EQ(with7.codec, Codec::kZstd);
  EXPECT_EQ(r.brick_labels(with7), (std::vector<std::uint32_t>{0, 7}));
  const BrickInfo& empty = r.brick(2, 0, 2, 1, 1);
  EXPECT_EQ(empty.codec, Codec::kUniform);
  EXPECT_EQ(r.brick_labels(empty), (std::vector<std::uint32_t>{0}));
  check_all_levels(path, v);
}

TEST(Reduction, MeanRoundsHalfUpExactly) {
  const std::int16_t a[2] = {-3, -2};  // -2.5 -> -2
  EXPECT_EQ(reduce_mean_i16(a, 2), -2);
  const std::int16_t b[2] = {2, 3};  // 2.5 -> 3
  EXPECT_EQ(reduce_mean_i16(b, 2), 3);
  const std::int16_t c[8] = {-32768, -32768, -32768, -32768, -32768, -32768, -32768, -32768};
  EXPECT_EQ(reduce_mean_i16(c, 8), -32768);
  const std::int16_t d[3] = {1000, -1000, 1};  // 1/3 -> 0
  EXPECT_EQ(reduce_mean_i16(d, 3), 0);
}

TEST(Reduction, GelWithZeroAlphaDoesNotBleedIntoTissue) {
  // 4 red tissue voxels (alpha 255) and 4 blue gel voxels (alpha 0).
  std::uint8_t ch[32];
  for (int i = 0; i < 8; ++i) {
    std::uint8_t tissue[4] = {200, 30, 20, 255}, gel[4] = {10, 40, 220, 0};
    std::memcpy(ch + 4 * i, i < 4 ? tissue : gel, 4);
  }
  auto r = reduce_rgba_alpha_weighted(ch, 8);
  EXPECT_EQ(r[0], 200);
  EXPECT_EQ(r[1], 30);
  EXPECT_EQ(r[2], 20);
  EXPECT_EQ(r[3], 128);  // (4 * 255) / 8 = 127.5 -> 128
  // All gel: plain mean of colours, alpha 0.
  auto g = reduce_rgba_alpha_weighted(ch + 16, 4);
  EXPECT_EQ(g[2], 220);
  EXPECT_EQ(g[3], 0);
}

TEST(Reduction, MajorityNeverInventsAnId) {
  std::mt19937 rng(99);
  for (int trial = 0; trial < 20000; ++trial) {
    int n = std::uniform_int_distribution<int>(1, 8)(rng);
    std::uint16_t ch[8];
    std::uniform_int_distribution<int> pick(0, trial % 2 ? 3 : 65535);
    for (int i = 0; i < n; ++i)
      ch[i] = std::uint16_t(pick(rng));
    std::uint16_t m = reduce_majority(ch, n);
    std::set<std::uint16_t> present(ch, ch + n);
    ASSERT_TRUE(present.count(m)) << "trial " << trial;
    int best = 0;
    for (std::uint16_t id : present)
      best = std::max<int>(best, int(std::count(ch, ch + n, id)));
    ASSERT_EQ(std::count(ch, ch + n, m), best) << "the result is a most frequent ID";
  }
  const std::uint16_t one_three[8] = {1, 1, 1, 1, 3, 3, 3, 3};
  EXPECT_EQ(reduce_majority(one_three, 8), 1) << "ties go to the smallest non-zero ID, never 2";
  const std::uint16_t zero_tie[2] = {0, 9};
  EXPECT_EQ(reduce_majority(zero_tie, 2), 9);
}

TEST(Reduction, LabelPyramidHoldsOnlyIdsOfItsChildren) {
  // Stripes of labels 1 and 3 side by side: no level may contain 2.
  Volume v = make_volume({33, 20, 18}, 1);
  for (std::size_t i = 0; i < v.data[2].size() / 2; ++i) {
    std::uint16_t id = (i % 33) % 2 ? 3 : 1;
    std::memcpy(&v.data[2][2 * i], &id, 2);
  }
  std::string path = temp_path("stripes.vpk");
  write(path, v, options_for(v, 4));
  Reader r = Reader::open(path);
  for (int l = 0; l < r.level_count(); ++l) {
    std::vector<std::uint8_t> lv = r.read_level(2, l);
    for (std::uint8_t id : lv)
      ASSERT_TRUE(id == 1 || id == 3) << "level " << l;
  }
}

TEST(Determinism, SameInputSameBytesWhateverThreads) {
  Volume v = make_volume({50, 40, 37}, 21, 300);
  std::string a = temp_path("a.vpk"), b = temp_path("b.vpk"), c = temp_path("c.vpk");
  write(a, v, options_for(v, 16, 1));
  write(b, v, options_for(v, 16, 2));
  write(c, v, options_for(v, 16, 5));
  auto ba = read_bytes(a);
  EXPECT_TRUE(ba == read_bytes(b));
  EXPECT_TRUE(ba == read_bytes(c));
  EXPECT_EQ(ba.size() % 1, 0u);
}

// The coarser levels' slabs in the scratch file (the path of large volumes) or in memory give the
// same bytes, and the nameless scratch file leaves nothing behind.
TEST(Determinism, SpilledCoarseLevelsGiveTheSameBytes) {
  Volume v = make_volume({50, 40, 37}, 22, 300);
  std::string a = temp_path("mem.vpk"), b = temp_path("spill.vpk");
  write(a, v, options_for(v, 8, 2));
  WriterOptions o = options_for(v, 8, 3);
  o.coarse_levels_memory_bytes = 0;
  write(b, v, o);
  EXPECT_TRUE(read_bytes(a) == read_bytes(b));
  check_all_levels(b, v);
  for (const auto& entry : std::filesystem::directory_iterator(temp_dir()))
    EXPECT_EQ(entry.path().string().find(".spill"), std::string::npos) << entry.path();
}

// The coarser levels' strips (compressed, or raw where zstd does not shrink them: the noisy
// inside of the volume) held all in memory, all in the scratch file, or split between the two at
// limits that fill up part way through a slab (so a refilled slab moves strips between memory and
// file), give the same bytes; level 1 has three slabs here (each refilled from the last).
TEST(Determinism, CoarseLevelStripsInMemoryFileOrBothGiveTheSameBytes) {
  Volume v = make_volume({61, 45, 37}, 23, 300);
  const std::string reference = temp_path("reference.vpk");
  write(reference, v, options_for(v, 8, 2));
  const auto expected = read_bytes(reference);
  for (std::uint64_t limit :
       {std::uint64_t(0), std::uint64_t(1) << 11, std::uint64_t(1) << 13, std::uint64_t(1) << 15}) {
    for (int threads : {1, 3}) {
      WriterOptions o = options_for(v, 8, threads);
      o.coarse_levels_memory_bytes = limit;
      const std::string path = temp_path("strips.vpk");
      write(path, v, o);
      EXPECT_TRUE(read_bytes(path) == expected) << "limit " << limit << ", threads " << threads;
      check_all_levels(path, v);
    }
  }
}

// A merge's path (provide_level0_slab + append_level1_slice, from encode_level0_slab's bricks and
// level-1 slices) writes the bytes append_slice writes: odd slice counts, a short last slab, uint8
// and uint16 labels, a slab count that is not a power of two.
TEST(Writer, Level1SlicesWithProvidedLevel0GiveTheSameBytes) {
  struct Shape {
    Dims dims;
    int edge;
    std::uint32_t max_label;
  };
  for (const Shape& sh :
       {Shape{{50, 40, 37}, 8, 300}, Shape{{33, 20, 21}, 4, 40}, Shape{{70, 30, 64}, 16, 40},
        Shape{{20, 20, 1}, 4, 40}, Shape{{7, 5, 3}, 8, 40}}) {  // the last: one level, no level 1
    Volume v = make_volume(sh.dims, 9, sh.max_label);
    const WriterOptions o = options_for(v, sh.edge, 2);
    std::string whole = temp_path("whole.vpk"), merged = temp_path("merged.vpk");
    write(whole, v, o);
    {
      Writer w(merged, o);
      const std::size_t plane = std::size_t(sh.dims[0] * sh.dims[1]);
      const std::int64_t e = sh.edge;
      for (std::int64_t bz = 0; bz < level0_slab_count(o); ++bz) {
        std::vector<const void*> slab;
        for (std::size_t c = 0; c < 3; ++c)
          slab.push_back(v.data[c].data() +
                         plane * std::size_t(bz * e) * (c == 0 ? 4 : 2));  // labels as uint16
        std::vector<std::vector<std::uint8_t>> level1;
        w.provide_level0_slab(bz, encode_level0_slab(o, bz, slab, &level1));
        const std::size_t n1 =
            level1[0].empty() ? 0 : std::size_t((std::min(e, sh.dims[2] - bz * e) + 1) / 2);
        append_level1_slices(w, level1, n1);
      }
      w.finish();
      EXPECT_EQ(w.slices_written(), sh.dims[2]);
    }
    EXPECT_TRUE(read_bytes(whole) == read_bytes(merged))
        << sh.dims[0] << "x" << sh.dims[1] << "x" << sh.dims[2] << " edge " << sh.edge;
  }
}

// The writer reduces full 2x2x2 blocks on fast paths (shift for means, equal-alpha shortcut,
// eight-equal-IDs shortcut) and the edges on the reduce_* functions: both must agree exactly
// with the naive reference on arbitrary values, not only the smooth phantom. Random alphas mix
// 0, 255 and any value; CT spans the whole int16 range; labels are random IDs (uint8 and
// uint16 stored types), with runs so that both majority paths are taken.
TEST(Reduction, FastPathsAgreeWithReferenceOnNoise) {
  for (std::uint32_t max_label : {40u, 400u}) {
    Volume v = make_volume({37, 22, 19}, 5, max_label);
    std::mt19937 rng(max_label);
    for (std::size_t i = 0; i < v.data[0].size(); i += 4) {
      for (int c = 0; c < 4; ++c)
        v.data[0][i + std::size_t(c)] = std::uint8_t(rng());
      const int pick = int(rng() % 4);
      if (pick < 2) v.data[0][i + 3] = pick == 0 ? 0 : 255;
    }
    for (auto& b : v.data[1])
      b = std::uint8_t(rng());
    for (std::size_t i = 0; i + 1 < v.data[2].size(); i += 2) {
      const std::uint16_t id =
          rng() % 3 == 0 ? 0 : std::uint16_t(v.label_table[rng() % v.label_table.size()].id);
      std::memcpy(&v.data[2][i], &id, 2);
      if (i + 3 < v.data[2].size() && rng() % 2) {  // a run of two equal IDs
        std::memcpy(&v.data[2][i + 2], &id, 2);
        i += 2;
      }
    }
    std::string path = temp_path("noise.vpk");
    write(path, v, options_for(v, 8, 3));
    check_all_levels(path, v);
  }
}

// The uniform-block shortcut of the colour reduction (eight equal children give themselves) must
// not take a block whose four rows are equal but whose two x children differ: colour and alpha
// vary along x only here (constant in y and z), uniform stretches in between.
TEST(Reduction, RowsEqualInYAndZButNotAlongXAreAveraged) {
  Volume v = make_volume({45, 12, 10}, 6, 40);
  const std::size_t plane = std::size_t(v.dims[0] * v.dims[1]);
  for (std::size_t i = 0; i < plane * std::size_t(v.dims[2]); ++i) {
    const std::size_t x = i % std::size_t(v.dims[0]);
    std::uint8_t* p = &v.data[0][4 * i];
    const bool flat = (x / 6) % 2 == 0;  // stretches of equal voxels
    p[0] = std::uint8_t(flat ? 90 : 17 * x);
    p[1] = std::uint8_t(flat ? 90 : 255 - 11 * x);
    p[2] = std::uint8_t(flat ? 90 : 3 * x);
    p[3] = std::uint8_t(flat ? 255 : (x % 3 == 0 ? 255 : 40 * (x % 5)));
  }
  std::string path = temp_path("rows.vpk");
  write(path, v, options_for(v, 4, 2));
  check_all_levels(path, v);
}

// A writer abandoned with slabs still being compressed joins its threads and leaves nothing.
TEST(Writer, AbandonedWithSlabsInFlightLeavesNoFile) {
  Volume v = make_volume({40, 30, 50}, 3);
  std::string path = temp_path("abandoned.vpk");
  {
    Writer w(path, options_for(v, 8, 3));
    const std::size_t plane = std::size_t(40 * 30);
    for (std::int64_t z = 0; z < 33; ++z) {
      w.append_slice({v.data[0].data() + plane * 4 * std::size_t(z),
                      v.data[1].data() + plane * 2 * std::size_t(z),
                      v.data[2].data() + plane * 2 * std::size_t(z)});
    }
    EXPECT_EQ(w.slices_written(), 33);
  }
  EXPECT_FALSE(std::filesystem::exists(path));
  for (const auto& entry : std::filesystem::directory_iterator(temp_dir()))
    EXPECT_EQ(entry.path().string().find("abandoned.vpk"), std::string::npos) << entry.path();
}

// Writing a finished brick fails (disk full) while other threads still make bricks of the same
// slab: the writer reports the file and its reason, and no thread touches the abandoned batch
// (it did: CI's Faults.RealFullFilesystem crashed with SIGSEGV; ASan names the use after free).
// Run in a child process: RLIMIT_FSIZE makes write() fail with EFBIG, as a full disk would.
TEST(Writer, WriteFailingWhileThreadsEncodeIsIoErrorNotACrash) {
  GTEST_FLAG_SET(death_test_style, "threadsafe");
  Volume v = make_volume({96, 80, 24}, 5);
  std::string path = temp_path("full_disk.vpk");
  EXPECT_EXIT(
      {
        std::signal(SIGXFSZ, SIG_IGN);
        struct rlimit limit {};
        getrlimit(RLIMIT_FSIZE, &limit);
        // Several tries, the limit falling at a different brick each time: the old code
        // crashed (or corrupted the heap) in about half of them.
        for (int attempt = 0; attempt < 12; ++attempt) {
          limit.rlim_cur = rlim_t(40 * 1024 + attempt * 3000);
          setrlimit(RLIMIT_FSIZE, &limit);
          try {
            write(path, v, options_for(v, 8, 4));  // 12 x 10 x 3 bricks of 8^3 per channel
            std::_Exit(4);  // wrote a file larger than the limit: the test is broken
          } catch (const vispack::IoError& e) {
            if (std::string(e.what()).find("full_disk.vpk") == std::string::npos) std::_Exit(3);
          }
        }
        std::_Exit(0);
      },
      ::testing::ExitedWithCode(0), "");
  EXPECT_FALSE(std::filesystem::exists(path));
}

// The threads of this process, from /proc/self/status.
int process_threads() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line))
    if (line.rfind("Threads:", 0) == 0) return std::stoi(line.substr(8));
  return -1;
}

// `threads` counts the calling thread (parallel_for's convention): a Writer of one thread starts
// no other, one of three starts two (Determinism.SameInputSameBytesWhateverThreads: same bytes).
TEST(Writer, ThreadsCountTheCallingThread) {
  Volume v = make_volume({40, 30, 20}, 3, 50);
  const int before = process_threads();
  ASSERT_GT(before, 0);
  for (int threads : {1, 3}) {
    Writer w(temp_path("threads" + std::to_string(threads) + ".vpk"), options_for(v, 8, threads));
    EXPECT_EQ(process_threads() - before, threads - 1) << threads << " threads";
  }
  EXPECT_EQ(process_threads(), before);  // joined when abandoned
}

TEST(Writer, RejectsBadOptionsAndMisuse) {
  Volume v = make_volume({8, 8, 4}, 1);
  WriterOptions o = options_for(v, 8);
  std::string path = temp_path("bad.vpk");
  auto with = [&](auto change) {
    WriterOptions x = o;
    change(x);
    return x;
  };
  EXPECT_THROW(Writer(path, with([](WriterOptions& x) { x.dims[1] = 0; })), std::invalid_argument);
  EXPECT_THROW(Writer(path, with([](WriterOptions& x) { x.brick_edge = 48; })),
               std::invalid_argument);
  EXPECT_THROW(Writer(path, with([](WriterOptions& x) { x.spacing_mm[2] = -1; })),
               std::invalid_argument);
  EXPECT_THROW(Writer(path, with([](WriterOptions& x) { x.channels.push_back(x.channels[0]); })),
               std::invalid_argument);
  EXPECT_THROW(Writer(path, with([](WriterOptions& x) {
                        x.label_table.push_back({0, "zero", {}});
                      })),
               std::invalid_argument);
  {
    Writer w(path, o);
    std::vector<const void*> one{v.data[0].data()};
    EXPECT_THROW(w.append_slice(one), std::invalid_argument);
    EXPECT_THROW(w.finish(), std::invalid_argument);  // no slices yet
  }
  EXPECT_FALSE(std::filesystem::exists(path)) << "an unfinished writer leaves nothing behind";
  // A label that does not fit uint8 (the table's max id is 40) is an input error.
  std::uint16_t big = 300;
  std::memcpy(&v.data[2][0], &big, 2);
  EXPECT_THROW(write(path, v, o), vispack::InputError);
  EXPECT_FALSE(std::filesystem::exists(path));
}

TEST(Metadata, GeometryAndTablesRoundTrip) {
  Volume v = make_volume({30, 20, 10}, 1);
  std::string path = temp_path("meta.vpk");
  write(path, v, options_for(v, 8));
  Reader r = Reader::open(path);
  EXPECT_EQ(r.metadata()["extra"]["provenance"]["tool"], "format tests");
  EXPECT_EQ(r.label_table().size(), v.label_table.size());
  EXPECT_EQ(r.label_table()[3].name, v.label_table[3].name);
  EXPECT_EQ(r.label_table()[3].colour, v.label_table[3].colour);
  // Level 1 voxel 0 covers level-0 voxels 0 and 1: its centre is half a voxel further.
  EXPECT_DOUBLE_EQ(r.origin_mm(1)[0], -10.0 + 0.5 * 0.33);
  EXPECT_DOUBLE_EQ(r.spacing_mm(2)[1], 0.5 * 4);
  EXPECT_EQ(r.version_major(), kFormatMajor);
  EXPECT_EQ(r.file_size(), read_bytes(path).size());
}

}  // namespace

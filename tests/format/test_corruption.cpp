// Corrupt, truncated and hostile files: every problem is a clear FormatError or a failed
// verify() naming the brick; nothing crashes or reads out of bounds (run under ASan+UBSan with
// -DVISPACK_SANITIZE=ON to check the latter).
#include <gtest/gtest.h>

#include <functional>

#include "format_test_util.h"
#include "vispack/common/hash.h"

using namespace vispack::format;
using namespace vispack::format::testing;
using vispack::FormatError;

namespace {

class Corruption : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    Volume v = make_volume({24, 20, 18}, 9);
    path_ = new std::string(temp_path("good.vpk"));
    write(*path_, v, options_for(v, 8));
    bytes_ = new std::vector<std::uint8_t>(read_bytes(*path_));
  }
  static void TearDownTestSuite() {
    delete path_;
    delete bytes_;
  }
  // Writes `bytes` to a scratch file and opens it.
  static Reader open_bytes(const std::vector<std::uint8_t>& bytes) {
    static const std::string scratch = temp_path("scratch.vpk");
    write_bytes(scratch, bytes);
    return Reader::open(scratch);
  }
  static void expect_refused(const std::vector<std::uint8_t>& bytes, const std::string& what,
                             const std::string& needle = "") {
    try {
      open_bytes(bytes);
      ADD_FAILURE() << what << ": opened without error";
    } catch (const FormatError& e) {
      std::string msg = e.what();
      EXPECT_NE(msg.find("scratch.vpk"), std::string::npos)
          << what << ": message names the file: " << msg;
      if (!needle.empty()) {
        EXPECT_NE(msg.find(needle), std::string::npos) << what << ": " << msg;
      }
    }
  }
  static std::string* path_;
  static std::vector<std::uint8_t>* bytes_;
};
std::string* Corruption::path_ = nullptr;
std::vector<std::uint8_t>* Corruption::bytes_ = nullptr;

TEST_F(Corruption, GoodFileVerifies) {
  Reader r = open_bytes(*bytes_);
  VerifyResult v = r.verify(true);
  EXPECT_TRUE(v.ok) << v.message;
  // Rebuilding without a change reproduces the file byte for byte (the test helpers are sound).
  EXPECT_TRUE(assemble(split(*bytes_)) == *bytes_);
}

TEST_F(Corruption, EveryPayloadByteFlipIsCaughtByVerify) {
  Reader good = Reader::open(*path_);
  std::mt19937 rng(17);
  int bricks_checked = 0, flips = 0;
  for (const BrickInfo& b : good.bricks()) {
    if (b.codec == Codec::kUniform) continue;
    ++bricks_checked;
    // First, last and 6 random bytes of every payload (exhaustive flips of all ~100 kB would
    // take minutes; xxHash64 detects any single-byte change, the samples check the wiring).
    std::vector<std::uint64_t> positions = {0, b.stored_size - 1};
    for (int i = 0; i < 6; ++i)
      positions.push_back(std::uniform_int_distribution<std::uint64_t>(0, b.stored_size - 1)(rng));
    for (std::uint64_t p : positions) {
      std::vector<std::uint8_t> bad = *bytes_;
      bad[b.offset + p] ^= std::uint8_t(1 + rng() % 255);
      Reader r = open_bytes(bad);  // the index is intact, so open succeeds
      VerifyResult v = r.verify(false, 1);
      ++flips;
      ASSERT_FALSE(v.ok) << "flip at payload byte " << p;
      ASSERT_TRUE(v.brick.has_value());
      EXPECT_EQ(v.brick->level, b.level);
      EXPECT_EQ(v.brick->channel, b.channel);
      EXPECT_EQ(v.brick->brick, b.brick);
      EXPECT_NE(v.message.find("checksum"), std::string::npos) << v.message;
      // A checked decode refuses the brick too.
      std::vector<std::uint8_t> out(r.brick_bytes(b.channel));
      EXPECT_THROW(r.decode_brick(b, out.data(), out.size(), true), FormatError);
    }
  }
  EXPECT_GT(bricks_checked, 20);
  EXPECT_EQ(flips, bricks_checked * 8);
}

TEST_F(Corruption, PaddingBytesAreCheckedToo) {
  Reader good = Reader::open(*path_);
  std::vector<std::uint64_t> pads = {128, 2000, 4095};
  for (const BrickInfo& b : good.bricks()) {
    if (b.codec != Codec::kUniform && (b.offset + b.stored_size) % 4096 != 0)
      pads.push_back(b.offset + b.stored_size);
  }
  const std::uint64_t meta_end = get_u64(*bytes_, 40) + get_u64(*bytes_, 48);
  const bool meta_pad = meta_end % 8 != 0;
  for (std::uint64_t p : pads) {
    std::vector<std::uint8_t> bad = *bytes_;
    bad[p] = 0x5A;
    VerifyResult v = open_bytes(bad).verify(false, 1);
    ASSERT_FALSE(v.ok) << "padding byte " << p;
    EXPECT_NE(v.message.find("padding"), std::string::npos) << v.message;
  }
  if (meta_pad) {
    // The metadata padding is inside the table checksum: open refuses it already.
    std::vector<std::uint8_t> bad = *bytes_;
    bad[meta_end] = 1;
    expect_refused(bad, "metadata padding", "checksum");
  }
}

TEST_F(Corruption, HeaderMetadataIndexFlipsFailTheTableChecksum) {
  const std::uint64_t moff = get_u64(*bytes_, 40);
  std::vector<std::uint64_t> positions = {
      20, 100, 119, 125, moff, moff + 10, bytes_->size() - 1, get_u64(*bytes_, 56) + 70};
  for (std::uint64_t p : positions) {
    std::vector<std::uint8_t> bad = *bytes_;
    bad[p] ^= 0x10;
    expect_refused(bad, "flip at " + std::to_string(p));
  }
}

TEST_F(Corruption, TruncationAtSixteenPoints) {
  for (int i = 0; i < 16; ++i) {
    std::size_t size = i == 15 ? bytes_->size() - 1 : bytes_->size() * std::size_t(i) / 15;
    std::vector<std::uint8_t> cut(bytes_->begin(), bytes_->begin() + std::ptrdiff_t(size));
    expect_refused(cut, "truncated to " + std::to_string(size),
                   size < 128 ? "truncated or not a vispack file" : "truncated");
  }
  std::vector<std::uint8_t> longer = *bytes_;
  longer.push_back(0);
  expect_refused(longer, "one byte appended", "extended");
}

TEST_F(Corruption, HostileMetadata) {
  Parts p = split(*bytes_);
  auto with_meta = [&](const std::function<void(nlohmann::json&)>& edit) {
    Parts q = p;
    nlohmann::json m = nlohmann::json::parse(q.meta);
    edit(m);
    q.meta = m.dump();
    return assemble(q);
  };
  auto with_text = [&](const std::string& text) {
    Parts q = p;
    q.meta = text;
    return assemble(q);
  };
  expect_refused(with_meta([](auto& m) { m["dims"] = {2147483648LL, 1, 1}; }), "dims 2^31", "dims");
  expect_refused(with_meta([](auto& m) {
                   m["dims"] = {9223372036854775807LL, 1, 1};
                 }),
                 "dims 2^63-1", "dims");
  expect_refused(with_meta([](auto& m) {
                   m["dims"] = {18446744073709551615ULL, 1, 1};
                 }),
                 "dims 2^64-1", "dims");
  expect_refused(with_meta([](auto& m) {
                   m["dims"] = {2147483647, 2147483647, 2147483647};
                 }),
                 "dims product overflow");
  expect_refused(with_meta([](auto& m) {
                   m["dims"] = {2147483647, 2147483647, 1};
                 }),
                 "too many bricks");
  expect_refused(with_meta([](auto& m) { m["dims"] = {-5, 1, 1}; }), "negative dim", "dims");
  expect_refused(with_meta([](auto& m) { m["dims"] = {"24", 20, 18}; }), "string dim", "dims");
  expect_refused(with_meta([](auto& m) { m["dims"] = {24, 20}; }), "two dims", "dims");
  expect_refused(with_meta([](auto& m) {
                   m["dims"] = {100000, 1, 1};
                 }),
                 "dims disagree with the index", "level_count");
  expect_refused(with_meta([](auto& m) { m["spacing_mm"][1] = -0.5; }), "negative spacing",
                 "spacing_mm");
  expect_refused(with_meta([](auto& m) { m["brick_edge"] = 16; }), "brick edge differs",
                 "brick_edge");
  expect_refused(with_meta([](auto& m) { m["channels"][0]["type"] = "float128"; }), "unknown type",
                 "float128");
  expect_refused(with_meta([](auto& m) { m["channels"][1]["name"] = "rgba"; }), "duplicate channel",
                 "channels");
  expect_refused(with_meta([](auto& m) { m["channels"].erase(2); }), "channel count", "channels");
  {
    // A label channel retyped uint8 -> uint16 passes every check open() can make without
    // decoding; its zstd bricks then decode to half the expected size: a FormatError, no overrun.
    Reader r = open_bytes(with_meta([](auto& m) { m["channels"][2]["type"] = "uint16"; }));
    EXPECT_THROW(r.read_level(2, 0), FormatError);
    EXPECT_FALSE(r.verify(true).ok);
  }
  expect_refused(with_meta([](auto& m) {
                   m["label_table"][0]["colour"] = {1, 2, 300};
                 }),
                 "colour 300", "colour");
  expect_refused(with_meta([](auto& m) { m.erase("format"); }), "missing key", "format");
  expect_refused(with_text("{\"format\": \"vispack\", \"dims\": [1, "), "truncated JSON",
                 "malformed");
  expect_refused(with_text("[]"), "JSON array", "not an object");
  expect_refused(with_text(std::string(200000, '[') + std::string(200000, ']')), "deep nesting",
                 "nested");
  expect_refused(with_text(std::string("\xff\xfe{}", 4)), "binary garbage", "malformed");
}

TEST_F(Corruption, HostileHeader) {
  Parts p = split(*bytes_);
  auto patched = [&](const std::function<void(std::vector<std::uint8_t>&)>& patch) {
    return assemble(p, patch);
  };
  expect_refused(patched([](auto& f) { f[0] = 'X'; }), "bad magic", "magic");
  expect_refused(patched([](auto& f) { f[8] = 2; }), "newer major", "newer");
  expect_refused(patched([](auto& f) { set_u32(f, 12, 256); }), "header size", "header_size");
  expect_refused(patched([](auto& f) { set_u32(f, 92, 48); }), "edge 48", "brick_edge");
  expect_refused(patched([](auto& f) { set_u32(f, 96, 9); }), "level count", "level_count");
  expect_refused(patched([](auto& f) { set_u32(f, 100, 0); }), "no channels", "channel_count");
  expect_refused(patched([](auto& f) { set_u32(f, 104, 1); }), "flags", "reserved");
  expect_refused(patched([](auto& f) { set_u64(f, 48, std::uint64_t(1) << 63); }),
                 "metadata size 2^63", "metadata_size");
  expect_refused(patched([](auto& f) { set_u64(f, 48, get_u64(f, 48) + 4096); }),
                 "metadata past end");
  expect_refused(patched([](auto& f) { set_u64(f, 64, std::uint64_t(1) << 40); }),
                 "index count 2^40", "index_count");
  expect_refused(patched([](auto& f) { set_u64(f, 64, (std::uint64_t(1) << 58) + 1); }),
                 "index bytes overflow");
  expect_refused(patched([](auto& f) { set_u64(f, 64, get_u64(f, 64) + 1); }), "index past end");
  expect_refused(patched([](auto& f) { set_u64(f, 80, ~std::uint64_t(0)); }), "labels count 2^64-1",
                 "labels_count");
  expect_refused(patched([](auto& f) { set_u64(f, 32, get_u64(f, 32) + 4096); }),
                 "payload end past metadata");
  expect_refused(patched([](auto& f) { set_u64(f, 32, 4097); }), "unaligned payload end");
  expect_refused(patched([](auto& f) { set_u64(f, 40, ~std::uint64_t(0) - 5); }),
                 "metadata offset 2^64", "metadata_offset");
}

TEST_F(Corruption, HostileIndexEntries) {
  Parts p = split(*bytes_);
  Reader good = Reader::open(*path_);
  // Two non-uniform bricks and one uniform brick to edit.
  std::vector<std::size_t> stored;
  std::size_t uniform = SIZE_MAX;
  for (std::size_t k = 0; k < good.bricks().size(); ++k) {
    if (good.bricks()[k].codec != Codec::kUniform)
      stored.push_back(k);
    else if (uniform == SIZE_MAX)
      uniform = k;
  }
  ASSERT_GE(stored.size(), 2u);
  ASSERT_NE(uniform, SIZE_MAX);
  const std::size_t a = stored[0], b = stored[1];
  const std::uint64_t pend = get_u64(*bytes_, 32);
  auto with_entry = [&](std::size_t k, const std::function<void(std::uint8_t*)>& edit) {
    Parts q = p;
    edit(q.index.data() + 64 * k);
    return assemble(q);
  };
  auto u64 = [](std::uint8_t* e, int off, std::uint64_t v) { std::memcpy(e + off, &v, 8); };
  auto u32 = [](std::uint8_t* e, int off, std::uint32_t v) { std::memcpy(e + off, &v, 4); };
  expect_refused(with_entry(a, [&](auto* e) { u64(e, 16, pend); }), "offset at payload end",
                 "payload");
  expect_refused(with_entry(a, [&](auto* e) { u64(e, 16, std::uint64_t(1) << 62); }),
                 "offset far past end", "payload");
  expect_refused(with_entry(a, [&](auto* e) { u64(e, 16, good.bricks()[a].offset + 1); }),
                 "unaligned offset", "multiple of 4096");
  expect_refused(with_entry(a, [&](auto* e) { u64(e, 16, 0); }), "offset inside the header",
                 "payload");
  expect_refused(with_entry(b, [&](auto* e) { u64(e, 16, good.bricks()[a].offset); }),
                 "overlapping bricks", "overlaps");
  expect_refused(with_entry(a, [&](auto* e) { u64(e, 24, ~std::uint64_t(0)); }), "size 2^64-1");
  expect_refused(with_entry(a, [&](auto* e) { u64(e, 24, std::uint64_t(1) << 40); }),
                 "size past end");
  expect_refused(with_entry(a, [&](auto* e) { e[14] = 9; }), "unknown codec", "codec");
  expect_refused(with_entry(a, [&](auto* e) { e[14] = 1; }), "raw with zstd size", "raw brick");
  expect_refused(with_entry(a, [&](auto* e) { e[15] = 1; }), "reserved byte", "reserved");
  expect_refused(with_entry(a, [&](auto* e) { u32(e, 0, 7); }), "wrong position", "expected");
  expect_refused(with_entry(a, [&](auto* e) { e[12] = 200; }), "wrong level", "expected");
  expect_refused(with_entry(uniform, [&](auto* e) { u64(e, 24, 4096); }), "uniform with payload",
                 "uniform");
  expect_refused(with_entry(uniform, [&](auto* e) { e[47] = 1; }), "min bytes past the voxel",
                 "min/max");
  // Label sets (channel 2 of level 0 starts after 2 * 27 bricks).
  const std::size_t lab = 2 * 27;
  ASSERT_GT(good.bricks()[lab].label_count, 0u);
  expect_refused(with_entry(lab, [&](auto* e) { u32(e, 56, 0xFFFFFFF0u); }), "label range overflow",
                 "label set");
  expect_refused(with_entry(lab, [&](auto* e) { u32(e, 60, 0); }), "empty label set", "label set");
  expect_refused(with_entry(0, [&](auto* e) { u32(e, 60, 1); }), "label set on ct", "label set");
}

TEST_F(Corruption, UndecodableZstdPayloadWithValidChecksum) {
  Reader good = Reader::open(*path_);
  const BrickInfo* z = nullptr;
  std::size_t k = 0;
  for (; k < good.bricks().size(); ++k) {
    if (good.bricks()[k].codec == Codec::kZstd) {
      z = &good.bricks()[k];
      break;
    }
  }
  ASSERT_NE(z, nullptr);
  Parts p = split(*bytes_);
  std::uint8_t* payload = p.payload.data() + (z->offset - 4096);
  for (std::uint64_t i = 4; i < z->stored_size; ++i)
    payload[i] = std::uint8_t(i * 31);  // keep the magic, garble the rest
  std::uint64_t sum = vispack::xxh64(payload, z->stored_size);
  std::memcpy(p.index.data() + 64 * k + 32, &sum, 8);
  Reader r = open_bytes(assemble(p));
  EXPECT_TRUE(r.verify(false).ok) << "checksums match: only decoding can find this";
  VerifyResult deep = r.verify(true);
  EXPECT_FALSE(deep.ok);
  std::vector<std::uint8_t> out(r.brick_bytes(z->channel));
  EXPECT_THROW(r.decode_brick(*z, out.data(), out.size()), FormatError);
  EXPECT_THROW(r.read_level(z->channel, z->level), FormatError);
}

TEST_F(Corruption, LimitsRefuseLargeButValidFiles) {
  ReaderLimits tight;
  tight.max_index_entries = 10;
  EXPECT_THROW(Reader::open(*path_, tight), FormatError);
  tight = ReaderLimits{};
  tight.max_metadata_bytes = 16;
  EXPECT_THROW(Reader::open(*path_, tight), FormatError);
}

TEST(Open, MissingFileIsAnIoError) {
  EXPECT_THROW(Reader::open(temp_path("does-not-exist.vpk")), vispack::IoError);
}

}  // namespace

// The viewer and bad packed files (docs/RELIABILITY.md, 'The viewer'):
//  - vispack-view refuses a corrupt or hostile file with one line "vispack-view: error: <file>:
//    ..." and exit 4, before any GL work;
//  - a brick whose payload fails its checksum is reported by the volume source (FormatError
//    naming the brick), and the headless viewer draws it as missing (zeros), prints one warning
//    naming the brick and still writes the picture with exit 0.
#include <gtest/gtest.h>

#include <cstdint>
#include <filesystem>
#include <iostream>
#include <random>
#include <sstream>
#include <vector>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/format/reader.h"
#include "vispack/format/writer.h"
#include "vispack/render/volume.h"

namespace fs = std::filesystem;
namespace format = vispack::format;
using vispack::test::bin;
using vispack::test::run_command;
using vispack::test::TempDir;

namespace {

constexpr std::int64_t kX = 40, kY = 32, kZ = 24;  // not multiples of the brick edge 16

// A noisy RGBA volume (every brick stored, none uniform), written with 16^3 bricks.
void write_noisy(const std::string& path) {
  std::vector<std::uint8_t> rgba(std::size_t(kX * kY * kZ * 4));
  std::mt19937 rng(5);
  for (auto& v : rgba)
    v = std::uint8_t(rng() % 64 + 100);
  format::WriterOptions o;
  o.dims = {kX, kY, kZ};
  o.brick_edge = 16;
  o.threads = 1;
  o.channels = {{"rgba", format::ChannelType::kRgba8}};
  format::write_volume(path, o, {rgba.data()});
}

std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);)
    if (!line.empty()) out.push_back(line);
  return out;
}

class ViewerFaults : public ::testing::Test {
 protected:
  void SetUp() override {
    good_ = dir_ / "good.vpk";
    write_noisy(good_);
    bytes_ = vispack::read_file(good_);
  }
  // Runs vispack-view headless on `file`; stderr only.
  int view(const std::string& file, std::string* err) const {
    return run_command("(" + bin("vispack-view") + " " + file + " --screenshot " +
                           (dir_ / "shot.png") + " --size 48x32 2>&1 >/dev/null)",
                       err);
  }
  std::string with(const std::string& name, const std::string& content) const {
    std::string p = dir_ / name;
    vispack::write_file_atomic(p, content);
    return p;
  }
  void expect_refused(const std::string& file) const {
    std::string err;
    EXPECT_EQ(view(file, &err), 4) << err;
    std::cout << "[ message  ] " << err;  // for docs/RELIABILITY.md
    auto lines = lines_of(err);
    ASSERT_EQ(lines.size(), 1u) << err;
    EXPECT_EQ(lines[0].rfind("vispack-view: error: " + file, 0), 0u) << lines[0];
  }

  TempDir dir_{"vispack-viewer-faults"};
  std::string good_, bytes_;
};

TEST_F(ViewerFaults, RefusesTextFile) {
  expect_refused(with("text.vpk", "not a volume\n"));
}

TEST_F(ViewerFaults, RefusesEmptyFile) {
  expect_refused(with("empty.vpk", ""));
}

TEST_F(ViewerFaults, RefusesTruncatedFile) {
  expect_refused(with("half.vpk", bytes_.substr(0, bytes_.size() / 2)));
}

TEST_F(ViewerFaults, RefusesHeaderOnly) {
  expect_refused(with("header.vpk", bytes_.substr(0, 64)));
}

TEST_F(ViewerFaults, RefusesHostileHeaderFields) {
  // Every 8-byte field of the first 128 bytes set to all ones, one at a time: offsets, sizes
  // and counts that point outside the file or overflow.
  for (std::size_t at = 8; at + 8 <= 128 && at + 8 <= bytes_.size(); at += 8) {
    std::string hostile = bytes_;
    for (std::size_t i = 0; i < 8; ++i)
      hostile[at + i] = char(0xff);
    std::string file = with("hostile.vpk", hostile);
    std::string err;
    const int rc = view(file, &err);
    EXPECT_EQ(rc, 4) << "field at " << at << ":\n" << err;
    EXPECT_EQ(lines_of(err).size(), 1u) << err;
    std::cout << "[ message  ] field " << at << ": " << err;  // for docs/RELIABILITY.md
  }
}

TEST_F(ViewerFaults, RefusesMissingFile) {
  std::string err;
  EXPECT_EQ(view(dir_ / "absent.vpk", &err), 3) << err;
  EXPECT_NE(err.find("absent.vpk"), std::string::npos) << err;
}

// The corrupt brick: rgba, level 0, brick (1, 1, 0); one payload byte flipped.
class CorruptBrick : public ViewerFaults {
 protected:
  void SetUp() override {
    ViewerFaults::SetUp();
    auto reader = format::Reader::open(good_);
    const format::BrickInfo& b = reader.brick(0, 0, 1, 1, 0);
    ASSERT_GT(b.stored_size, 0u);
    std::string bad = bytes_;
    bad[std::size_t(b.offset + b.stored_size / 2)] ^= 0x5a;
    corrupt_ = with("corrupt.vpk", bad);
  }
  std::string corrupt_;
};

TEST_F(CorruptBrick, SourceReportsTheBrick) {
  auto source = vispack::render::open_packed(corrupt_);
  std::vector<std::uint8_t> out(16 * 16 * 16 * 4);
  vispack::render::Region ok{{0, 0, 0}, {16, 16, 16}};
  EXPECT_NO_THROW(source->read_region(vispack::render::Channel::kRgba, 0, ok, out.data()));
  vispack::render::Region bad{{16, 16, 0}, {16, 16, 16}};
  try {
    source->read_region(vispack::render::Channel::kRgba, 0, bad, out.data());
    ADD_FAILURE() << "corrupt brick read without error";
  } catch (const vispack::FormatError& e) {
    EXPECT_NE(std::string(e.what()).find("brick (1, 1, 0)"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("checksum"), std::string::npos) << e.what();
  }
}

TEST_F(CorruptBrick, HeadlessViewerWarnsAndShowsItMissing) {
  std::string err;
  if (view(good_, &err) != 0) GTEST_SKIP() << "no headless OpenGL here: " << err;
  const std::string good_png = vispack::read_file(dir_ / "shot.png");
  fs::remove(dir_ / "shot.png");
  ASSERT_EQ(view(corrupt_ + " --level 0", &err), 0) << err;
  std::cout << "[ message  ] " << err;  // for docs/RELIABILITY.md
  auto lines = lines_of(err);
  ASSERT_EQ(lines.size(), 1u) << err;
  EXPECT_EQ(lines[0].rfind("vispack-view: warning: " + corrupt_, 0), 0u) << lines[0];
  EXPECT_NE(lines[0].find("brick (1, 1, 0)"), std::string::npos) << lines[0];
  EXPECT_NE(lines[0].find("shown as missing"), std::string::npos) << lines[0];
  ASSERT_TRUE(fs::exists(dir_ / "shot.png"));
  // The hole shows: the picture differs from the intact file's.
  EXPECT_NE(vispack::read_file(dir_ / "shot.png"), good_png);
}

}  // namespace

// Command-line tests: vispack-info / vispack-extract exit codes and outputs, and the Python
// reader (scripts/vispack_read.py, written from SPEC.md alone) against the C++ reader.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <tuple>
#ifdef VISPACK_TEST_HAVE_OIIO
#include <OpenImageIO/imageio.h>
#endif

#include "format_test_util.h"
#include "vispack/common/nrrd.h"

using namespace vispack::format;
using namespace vispack::format::testing;

namespace {

struct Result {
  int code;
  std::string out, err;
};

Result run(const std::string& command) {
  const std::string out = temp_path("stdout.txt"), err = temp_path("stderr.txt");
  int status = std::system((command + " >" + out + " 2>" + err).c_str());
  Result r{WIFEXITED(status) ? WEXITSTATUS(status) : -1, vispack::read_file(out),
           vispack::read_file(err)};
  return r;
}

#ifdef VISPACK_TEST_HAVE_OIIO
// An image read back through OpenImageIO, samples interleaved.
struct Image {
  int width = 0, height = 0, channels = 0, bits = 0;
  std::vector<std::uint8_t> u8;
  std::vector<std::uint16_t> u16;
};
Image read_image(const std::string& path) {
  Image img;
  auto in = OIIO::ImageInput::open(path);
  if (!in) {
    ADD_FAILURE() << path << ": " << OIIO::geterror();
    return img;
  }
  const OIIO::ImageSpec& spec = in->spec();
  img.width = spec.width;
  img.height = spec.height;
  img.channels = spec.nchannels;
  img.bits = int(spec.format.size()) * 8;
  const std::size_t n = std::size_t(img.width) * img.height * img.channels;
  if (img.bits == 16) {
    img.u16.resize(n);
    in->read_image(0, 0, 0, img.channels, OIIO::TypeDesc::UINT16, img.u16.data());
  } else {
    img.u8.resize(n);
    in->read_image(0, 0, 0, img.channels, OIIO::TypeDesc::UINT8, img.u8.data());
  }
  in->close();
  return img;
}
#endif

const std::string kBin = VISPACK_BIN_DIR;
const std::string kInfo = kBin + "/vispack-info";
const std::string kExtract = kBin + "/vispack-extract";

class Cli : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    volume_ = new Volume(make_volume({45, 30, 20}, 3, 300));
    path_ = new std::string(temp_path("cli.vpk"));
    write(*path_, *volume_, options_for(*volume_, 8));
  }
  static void TearDownTestSuite() {
    delete volume_;
    delete path_;
  }
  static Volume* volume_;
  static std::string* path_;
};
Volume* Cli::volume_ = nullptr;
std::string* Cli::path_ = nullptr;

TEST_F(Cli, InfoPrintsAndVerifies) {
  Result r = run(kInfo + " " + *path_);
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("45 x 30 x 20"), std::string::npos) << r.out;
  r = run(kInfo + " --json --verify " + *path_);
  ASSERT_EQ(r.code, 0) << r.err;
  auto j = nlohmann::json::parse(r.out);
  EXPECT_EQ(j["verify"]["ok"], true);
  EXPECT_EQ(j["channels"][1]["name"], "ct");
  EXPECT_EQ(j["channels"][2]["type"], "uint16");
  EXPECT_EQ(run(kInfo + " --help").code, 0);
  EXPECT_EQ(run(kInfo).code, 2);
  EXPECT_EQ(run(kInfo + " --bogus " + *path_).code, 2);
  Result missing = run(kInfo + " " + temp_path("missing.vpk"));
  EXPECT_EQ(missing.code, 3);
  EXPECT_NE(missing.err.find("vispack-info: error: "), std::string::npos) << missing.err;
}

// The text output is a short summary: the writer's metadata one line per key, a list of slice
// numbers as ranges (a Visible Human male's 1,871 numbers in a few words), never a raw JSON dump;
// --json keeps every number.
TEST(InfoText, MetadataIsSummarisedWithNumbersAsRanges) {
  Volume v = make_volume({16, 12, 10}, 5);
  WriterOptions o = options_for(v, 8);
  std::vector<int> numbers;
  for (int n = 1001; n <= 2872; ++n)
    if (n != 1500) numbers.push_back(n);
  o.extra_metadata = {
      {"name", "male"},
      {"slices",
       {{"count", numbers.size()},
        {"numbers", numbers},
        {"missing_numbers", {1500}},
        {"black", nlohmann::json::array()}}},
      {"registration", {{"mean_quality", 0.987654}, {"jumps", {7, 8, 9, 40}}}},
      {"provenance", {{"tool", "format tests"}, {"input_hashes", {{"palette", ""}}}}}};
  const std::string path = temp_path("info-text.vpk");
  write(path, v, o);
  Result r = run(kInfo + " " + path);
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* line :
       {"name:        male\n",
        "slices:      black none, count 1871, missing_numbers 1500, numbers 1871: 1001..1499, "
        "1501..2872\n",
        "registration: jumps 4: 7..9, 40, mean_quality 0.9877\n",
        "provenance:  input_hashes (palette -), tool format tests\n"})
    EXPECT_NE(r.out.find(line), std::string::npos) << "no line '" << line << "' in\n" << r.out;
  EXPECT_EQ(r.out.find("1002"), std::string::npos) << r.out;
  EXPECT_EQ(r.out.find('{'), std::string::npos) << "raw JSON in the text output:\n" << r.out;
  Result j = run(kInfo + " --json " + path);
  ASSERT_EQ(j.code, 0) << j.err;
  EXPECT_EQ(nlohmann::json::parse(j.out)["metadata"]["extra"]["slices"]["numbers"],
            nlohmann::json(numbers));
}

TEST_F(Cli, VerifyNamesTheBadBrickAndExits4) {
  Reader good = Reader::open(*path_);
  const BrickInfo* victim = nullptr;
  for (const BrickInfo& b : good.bricks()) {
    if (b.codec != Codec::kUniform && b.level == 1) {
      victim = &b;
      break;
    }
  }
  ASSERT_NE(victim, nullptr);
  auto bytes = read_bytes(*path_);
  bytes[victim->offset + victim->stored_size / 2] ^= 0x01;
  const std::string bad = temp_path("bad.vpk");
  write_bytes(bad, bytes);
  Result r = run(kInfo + " --verify " + bad);
  EXPECT_EQ(r.code, 4);
  const std::string name =
      vispack::cat("vispack-info: finding 8: level 1 channel ",
                   good.channels()[std::size_t(victim->channel)].name, " brick (", victim->brick[0],
                   ",", victim->brick[1], ",", victim->brick[2], "): payload checksum mismatch");
  EXPECT_EQ(r.err.rfind(name, 0), 0u) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << "one line: " << r.err;
  // Without --verify the file still opens (the index is intact).
  EXPECT_EQ(run(kInfo + " " + bad).code, 0);
  // A truncated file is refused by open: exit 4.
  bytes.resize(bytes.size() / 2);
  write_bytes(bad, bytes);
  EXPECT_EQ(run(kInfo + " " + bad).code, 4);
  EXPECT_EQ(run(kExtract + " " + bad + " --channel ct -o " + temp_path("x.nrrd")).code, 4);
}

TEST_F(Cli, ExtractNrrdMatchesTheReaderWithSpacingAndOrigin) {
  Reader r = Reader::open(*path_);
  for (const char* channel : {"rgba", "ct", "labels"}) {
    for (int level : {0, 1}) {
      const std::string out = temp_path(std::string(channel) + ".nrrd");
      Result run_result = run(kExtract + " " + *path_ + " --channel " + channel + " --level " +
                              std::to_string(level) + " -o " + out);
      ASSERT_EQ(run_result.code, 0) << run_result.err;
      vispack::NrrdVolume v = vispack::read_nrrd(out);
      EXPECT_EQ(v.dims, r.dims(level));
      EXPECT_TRUE(v.data == r.read_level(channel, level)) << channel << " level " << level;
      for (int a = 0; a < 3; ++a) {
        // NRRD stores decimal text: 1e-9 mm is far below any printed precision loss that matters.
        EXPECT_NEAR(v.spacing_mm[a], r.spacing_mm(level)[a], 1e-9);
        EXPECT_NEAR(v.origin_mm[a], r.origin_mm(level)[a], 1e-9);
      }
      EXPECT_EQ(v.components, std::string(channel) == "rgba" ? 4 : 1);
    }
  }
}

TEST_F(Cli, ExtractSliceImagesAndUsageErrors) {
  const std::string png = temp_path("ct.png");
  Result r = run(kExtract + " " + *path_ + " --channel ct --z 7 -o " + png);
  if (r.code == 2 && r.err.find("no OpenImageIO") != std::string::npos)
    GTEST_SKIP() << "built without OpenImageIO";
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string tif = temp_path("rgba.tif");
  const Result tif_run = run(kExtract + " " + *path_ + " --channel rgba --level 1 --z 3 -o " + tif);
#ifdef VISPACK_TEST_HAVE_OIIO
  EXPECT_EQ(tif_run.code, 0) << tif_run.err;
  // The images hold the slice, pixel for pixel: CT as 16-bit HU + 32768, rgba as 8-bit RGBA of
  // the level asked for (compared with the reader's level, itself checked in format_roundtrip).
  Reader reader = Reader::open(*path_);
  {
    const Image img = read_image(png);
    ASSERT_EQ(img.width, 45);
    ASSERT_EQ(img.height, 30);
    ASSERT_EQ(img.channels, 1);
    ASSERT_EQ(img.bits, 16);
    const std::vector<std::uint8_t> level = reader.read_level("ct", 0);
    std::int64_t wrong = 0;
    for (std::size_t i = 0; i < std::size_t(45 * 30); ++i) {
      std::int16_t hu;
      std::memcpy(&hu, level.data() + 2 * (std::size_t(45 * 30) * 7 + i), 2);
      if (img.u16[i] != std::uint16_t(std::int32_t(hu) + 32768)) ++wrong;
    }
    EXPECT_EQ(wrong, 0);
  }
  {
    const Image img = read_image(tif);
    const auto dims = reader.dims(1);
    ASSERT_EQ(img.width, dims[0]);
    ASSERT_EQ(img.height, dims[1]);
    ASSERT_EQ(img.channels, 4);
    ASSERT_EQ(img.bits, 8);
    const std::vector<std::uint8_t> level = reader.read_level("rgba", 1);
    const std::size_t plane = std::size_t(dims[0] * dims[1]) * 4;
    EXPECT_TRUE(
        std::equal(img.u8.begin(), img.u8.end(), level.begin() + std::ptrdiff_t(plane * 3)));
  }
#else
  // The lean build (VISPACK_WITH_OPENIMAGEIO=OFF) writes PNG only: the TIFF is refused, naming it.
  EXPECT_EQ(tif_run.code, 3) << tif_run.err;
  EXPECT_NE(tif_run.err.find(tif + ": cannot write tiff: this build has no OpenImageIO"),
            std::string::npos)
      << tif_run.err;
  EXPECT_FALSE(std::filesystem::exists(tif));
#endif
  EXPECT_EQ(run(kExtract + " " + *path_ + " --channel nope -o " + temp_path("n.nrrd")).code, 2);
  EXPECT_EQ(run(kExtract + " " + *path_ + " --channel ct --level 9 -o " + temp_path("n.nrrd")).code,
            2);
  EXPECT_EQ(run(kExtract + " " + *path_ + " --channel ct --z 20 -o " + temp_path("n.png")).code, 2);
  EXPECT_EQ(run(kExtract + " " + *path_ + " --channel ct -o " + temp_path("n.png")).code, 2);
  EXPECT_EQ(run(kExtract + " " + *path_ + " --channel ct -o " + temp_path("n.xyz")).code, 2);
  EXPECT_EQ(run(kExtract + " " + *path_ + " --channel ct").code, 2);
  EXPECT_EQ(run(kExtract + " --help").code, 0);
}

// --window C:W: an 8-bit preview of a CT slice, each pixel the HU mapped through the window
// (0 at C - W/2, 255 at C + W/2, rounded, clamped); --preview is --window 40:400. One line on
// stdout names the file written.
TEST_F(Cli, ExtractCtPreviewThroughAWindow) {
  const std::string png = temp_path("ct-window.png");
  Result r = run(kExtract + " " + *path_ + " --channel ct --z 7 --window -100:600 -o " + png);
  if (r.code == 2 && r.err.find("no OpenImageIO") != std::string::npos)
    GTEST_SKIP() << "built without OpenImageIO";
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out,
            "wrote " + png + " (ct, level 0, z 7: 45 x 30, 8-bit grey, window -100:600 HU)\n");
  const std::string preview = temp_path("ct-preview.png");
  Result p = run(kExtract + " " + *path_ + " --channel ct --z 7 --preview -o " + preview);
  ASSERT_EQ(p.code, 0) << p.err;
  EXPECT_NE(p.out.find("window 40:400 HU"), std::string::npos) << p.out;
#ifdef VISPACK_TEST_HAVE_OIIO
  Reader reader = Reader::open(*path_);
  const std::vector<std::uint8_t> level = reader.read_level("ct", 0);
  for (const auto& [file, low, width] :
       {std::tuple{png, -400.0, 600.0}, std::tuple{preview, -160.0, 400.0}}) {
    const Image img = read_image(file);
    ASSERT_EQ(img.width, 45);
    ASSERT_EQ(img.height, 30);
    ASSERT_EQ(img.channels, 1);
    ASSERT_EQ(img.bits, 8);
    std::int64_t wrong = 0, black = 0, white = 0;
    for (std::size_t i = 0; i < std::size_t(45 * 30); ++i) {
      std::int16_t hu;
      std::memcpy(&hu, level.data() + 2 * (std::size_t(45 * 30) * 7 + i), 2);
      const double grey = std::clamp((double(hu) - low) / width * 255.0, 0.0, 255.0);
      if (std::abs(double(img.u8[i]) - grey) > 0.5 + 1e-9) ++wrong;
      black += img.u8[i] == 0;
      white += img.u8[i] == 255;
    }
    EXPECT_EQ(wrong, 0) << file;
    EXPECT_LT(black + white, 45 * 30) << file << ": every pixel clipped";
  }
#endif
  // Usage errors: not the ct channel, a bad window, a window for a .nrrd, both options.
  for (const std::string& bad :
       {" --channel rgba --z 1 --window 40:400 -o " + temp_path("w.png"),
        " --channel ct --z 1 --window 40:0 -o " + temp_path("w.png"),
        " --channel ct --z 1 --window 40 -o " + temp_path("w.png"),
        " --channel ct --window 40:400 -o " + temp_path("w.nrrd"),
        " --channel ct --z 1 --window 40:400 --preview -o " + temp_path("w.png")}) {
    Result u = run(kExtract + " " + *path_ + bad);
    EXPECT_EQ(u.code, 2) << bad << ": " << u.err;
    EXPECT_EQ(u.err.rfind("vispack-extract: error: ", 0), 0u) << u.err;
  }
  // The exact export is unchanged and says so.
  const std::string exact = temp_path("ct-exact.png");
  Result e = run(kExtract + " " + *path_ + " --channel ct --z 7 -o " + exact);
  ASSERT_EQ(e.code, 0) << e.err;
  EXPECT_EQ(e.out, "wrote " + exact + " (ct, level 0, z 7: 45 x 30, 16-bit grey = HU + 32768)\n");
}

TEST_F(Cli, PythonReaderAgreesVoxelForVoxel) {
  if (!std::filesystem::exists("/usr/bin/python3")) GTEST_SKIP() << "no /usr/bin/python3";
  const std::string script = std::string(VISPACK_SOURCE_DIR) + "/scripts/vispack_read.py";
  Result probe = run("/usr/bin/python3 -c 'import numpy, zstandard'");
  if (probe.code != 0) GTEST_SKIP() << "python3-numpy or python3-zstandard missing: " << probe.err;
  Reader r = Reader::open(*path_);
  // Level 0 with --verify (checks the pure-Python xxHash64 against the C++ checksums).
  for (int level = 0; level < r.level_count(); ++level) {
    for (const auto& ch : r.channels()) {
      const std::string raw = temp_path(ch.name + ".bin");
      Result p = run("/usr/bin/python3 " + script + " " + *path_ +
                     (level == 0 && ch.name == "rgba" ? " --verify" : "") + " --channel " +
                     ch.name + " --level " + std::to_string(level) + " --raw " + raw);
      ASSERT_EQ(p.code, 0) << p.err;
      auto got = read_bytes(raw);
      EXPECT_TRUE(got == r.read_level(ch.name, level)) << ch.name << " level " << level;
    }
  }
  // A flipped payload byte: the Python verifier exits 4 too.
  auto bytes = read_bytes(*path_);
  for (const BrickInfo& b : r.bricks()) {
    if (b.codec != Codec::kUniform) {
      bytes[b.offset] ^= 0x80;
      break;
    }
  }
  const std::string bad = temp_path("pybad.vpk");
  write_bytes(bad, bytes);
  Result p = run("/usr/bin/python3 " + script + " --verify " + bad);
  EXPECT_EQ(p.code, 4) << p.err;
  EXPECT_NE(p.err.find("checksum"), std::string::npos) << p.err;
}

}  // namespace

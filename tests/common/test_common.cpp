// Tests of vispack_common: atomic files, NRRD round trips and errors, command lines, slice ranges,
// parallel_for, exit codes and hashes.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/resource.h>
#include <unistd.h>

#include <atomic>
#include <csignal>
#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/common/exit_codes.h"
#include "vispack/common/hash.h"
#include "vispack/common/nrrd.h"
#include "vispack/common/parallel.h"

namespace fs = std::filesystem;
using namespace vispack;

namespace {

using vispack::test::TempDir;

std::size_t count_files(const fs::path& dir) {
  return std::distance(fs::directory_iterator(dir), fs::directory_iterator());
}

}  // namespace

TEST(AtomicFile, CommitPublishesCompleteFile) {
  TempDir dir;
  AtomicFile file(dir / "out.bin");
  file.write("hello ");
  EXPECT_FALSE(fs::exists(dir / "out.bin"));  // nothing at the destination before commit
  file.write("world");
  file.commit();
  EXPECT_EQ(read_file(dir / "out.bin"), "hello world");
  EXPECT_EQ(count_files(dir.path()), 1u);  // no temporary left behind
}

TEST(AtomicFile, AbandonedWriteKeepsOldContentAndLeavesNoTemp) {
  TempDir dir;
  write_file_atomic(dir / "out.txt", "old");
  {
    AtomicFile file(dir / "out.txt");
    file.write("new but never committed");
  }
  EXPECT_EQ(read_file(dir / "out.txt"), "old");
  EXPECT_EQ(count_files(dir.path()), 1u);
}

TEST(AtomicFile, PwritePatchesWithoutMovingAppendPosition) {
  TempDir dir;
  AtomicFile file(dir / "p.bin");
  file.write("XXXXtail");
  file.pwrite("head", 4, 0);
  file.write("!");
  file.commit();
  EXPECT_EQ(read_file(dir / "p.bin"), "headtail!");
}

TEST(AtomicFile, MissingFolderIsIoErrorNamingPath) {
  try {
    AtomicFile file("/nonexistent-vispack-dir/x.bin");
    FAIL() << "expected IoError";
  } catch (const IoError& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent-vispack-dir/x.bin"), std::string::npos);
  }
}

TEST(AtomicFile, FileSizeLimitIsIoErrorNotPartialFile) {
  TempDir dir;
  // RLIMIT_FSIZE makes write() fail with EFBIG (SIGXFSZ ignored), as a full disk would.
  struct rlimit old_limit {};
  getrlimit(RLIMIT_FSIZE, &old_limit);
  auto old_handler = std::signal(SIGXFSZ, SIG_IGN);
  struct rlimit limit = old_limit;
  limit.rlim_cur = 4096;
  setrlimit(RLIMIT_FSIZE, &limit);
  std::string big(10000, 'x');
  bool threw = false;
  try {
    write_file_atomic(dir / "big.bin", big);
  } catch (const IoError& e) {
    threw = true;
    EXPECT_NE(std::string(e.what()).find("big.bin"), std::string::npos);
  }
  setrlimit(RLIMIT_FSIZE, &old_limit);
  std::signal(SIGXFSZ, old_handler);
  EXPECT_TRUE(threw);
  EXPECT_FALSE(fs::exists(dir / "big.bin"));
  EXPECT_EQ(count_files(dir.path()), 0u);
}

// append_from copies a byte range of another open file onto the end, file to file
// (copy_file_range) or through a buffer (copy_range false, the way for file systems that refuse
// the first): the same bytes both ways, appended after what was written before, the append
// position moved; a source shorter than the range is an IoError naming it, and nothing is
// published.
TEST(AtomicFile, AppendFromCopiesARangeOfAnotherFileBothWays) {
  TempDir dir;
  std::string source(3 * 1024 * 1024 + 77, '\0');  // over the buffer of the second way
  for (std::size_t i = 0; i < source.size(); ++i)
    source[i] = char(i * 2654435761u >> 24);
  write_file_atomic(dir / "source.bin", source);
  const int fd = ::open((dir / "source.bin").c_str(), O_RDONLY);
  ASSERT_GE(fd, 0);
  for (bool copy_range : {true, false}) {
    const std::string name = copy_range ? "range.bin" : "buffer.bin";
    AtomicFile file(dir / name);
    file.write("head");
    file.append_from(fd, 5, source.size() - 9, "source.bin", copy_range);
    file.append_from(fd, 0, 0, "source.bin", copy_range);  // nothing
    file.append_from(fd, 1, 2, "source.bin", copy_range);
    file.write("!");
    EXPECT_EQ(file.size(), 4 + source.size() - 9 + 2 + 1);
    file.commit();
    EXPECT_EQ(read_file(dir / name),
              "head" + source.substr(5, source.size() - 9) + source.substr(1, 2) + "!")
        << (copy_range ? "copy_file_range" : "pread and write");
    AtomicFile shorter(dir / ("short-" + name));
    try {
      shorter.append_from(fd, source.size() - 10, 11, "source.bin", copy_range);
      ADD_FAILURE() << "a range past the end of the source was copied";
    } catch (const IoError& e) {
      EXPECT_NE(std::string(e.what()).find("source.bin: ends at byte"), std::string::npos)
          << e.what();
    }
  }
  ::close(fd);
  EXPECT_FALSE(fs::exists(dir / "short-range.bin"));
}

TEST(ReadFile, RefusesOverLimitAndMissing) {
  TempDir dir;
  write_file_atomic(dir / "a", "0123456789");
  EXPECT_THROW(read_file(dir / "a", 5), IoError);
  EXPECT_EQ(read_file(dir / "a", 10), "0123456789");
  EXPECT_THROW(read_file(dir / "missing"), IoError);
}

class NrrdRoundTrip : public ::testing::TestWithParam<bool> {};

TEST_P(NrrdRoundTrip, ScalarAndColourVolumesSurviveBitExact) {
  TempDir dir;
  bool gzip = GetParam();
  NrrdVolume ct;
  ct.type = NrrdType::kInt16;
  ct.dims = {5, 3, 7};
  ct.spacing_mm = {0.33, 0.5, 1.25};
  ct.origin_mm = {-10.5, 2.0, 3.25};
  ct.data.resize(ct.byte_size());
  for (std::size_t i = 0; i < ct.voxel_count(); ++i)
    ct.as<std::int16_t>()[i] = std::int16_t(i * 97 - 1024);
  write_nrrd(dir / "ct.nrrd", ct, gzip);
  NrrdVolume back = read_nrrd(dir / "ct.nrrd");
  EXPECT_EQ(back.type, NrrdType::kInt16);
  EXPECT_EQ(back.components, 1);
  EXPECT_EQ(back.dims, ct.dims);
  for (int a = 0; a < 3; ++a) {
    EXPECT_DOUBLE_EQ(back.spacing_mm[a], ct.spacing_mm[a]);
    EXPECT_DOUBLE_EQ(back.origin_mm[a], ct.origin_mm[a]);
  }
  EXPECT_EQ(back.data, ct.data);

  NrrdVolume rgb;
  rgb.type = NrrdType::kUint8;
  rgb.components = 3;
  rgb.dims = {4, 2, 1};
  rgb.data.resize(rgb.byte_size());
  for (std::size_t i = 0; i < rgb.data.size(); ++i)
    rgb.data[i] = std::uint8_t(i * 11);
  write_nrrd(dir / "rgb.nrrd", rgb, gzip);
  NrrdVolume rgb_back = read_nrrd(dir / "rgb.nrrd");
  EXPECT_EQ(rgb_back.components, 3);
  EXPECT_EQ(rgb_back.dims, rgb.dims);
  EXPECT_EQ(rgb_back.data, rgb.data);
}
INSTANTIATE_TEST_SUITE_P(RawAndGzip, NrrdRoundTrip, ::testing::Values(false, true));

TEST(Nrrd, TruncatedAndBadFilesAreFormatErrors) {
  TempDir dir;
  NrrdVolume v;
  v.dims = {8, 8, 8};
  v.data.assign(v.byte_size(), 7);
  write_nrrd(dir / "v.nrrd", v);
  std::string bytes = read_file(dir / "v.nrrd");
  write_file_atomic(dir / "trunc.nrrd", bytes.substr(0, bytes.size() - 10));
  EXPECT_THROW(read_nrrd(dir / "trunc.nrrd"), FormatError);
  write_file_atomic(dir / "magic.nrrd", "PNG nonsense\n\n");
  EXPECT_THROW(read_nrrd(dir / "magic.nrrd"), FormatError);
  write_file_atomic(dir / "huge.nrrd",
                    "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4000000000 4000000000 4000000000\n"
                    "encoding: raw\n\n");
  EXPECT_THROW(read_nrrd(dir / "huge.nrrd"), FormatError);
  write_file_atomic(dir / "type.nrrd",
                    "NRRD0004\ntype: quaternion\ndimension: 3\nsizes: 1 1 1\nencoding: raw\n\nx");
  EXPECT_THROW(read_nrrd(dir / "type.nrrd"), FormatError);
}

namespace {
int run_args(std::vector<std::string> words, const std::function<int(Args&)>& body) {
  std::vector<char*> argv;
  for (auto& w : words)
    argv.push_back(w.data());
  return run_main("vispack-test", int(argv.size()), argv.data(), body);
}
}  // namespace

TEST(Args, ParsesFlagsOptionsAndPositionals) {
  int rc = run_args({"prog", "file.vpk", "--level=2", "--json", "--channel", "ct"}, [](Args& args) {
    args.describe("FILE", "test");
    EXPECT_TRUE(args.flag("--json", "json"));
    EXPECT_FALSE(args.flag("--verify", "verify"));
    EXPECT_EQ(args.option_int("--level", "L", "level").value_or(-1), 2);
    EXPECT_EQ(args.option("--channel", "NAME", "channel").value_or(""), "ct");
    EXPECT_EQ(args.positional("FILE", "file"), "file.vpk");
    args.done();
    return 0;
  });
  EXPECT_EQ(rc, 0);
}

TEST(Args, UnknownOptionAndBadValueAreUsageErrors) {
  auto body = [](Args& args) {
    args.option_int("--level", "L", "level");
    args.done();
    return 0;
  };
  EXPECT_EQ(run_args({"prog", "--bogus"}, body), int(ExitCode::kUsage));
  EXPECT_EQ(run_args({"prog", "--level", "two"}, body), int(ExitCode::kUsage));
  EXPECT_EQ(run_args({"prog", "--level"}, body), int(ExitCode::kUsage));
  EXPECT_EQ(run_args({"prog", "--help"}, body), 0);
}

TEST(Args, AnUnknownOptionIsNamedBeforeAMissingPositional) {
  // "vispack-info --bogus": the message names --bogus, the real mistake, not the missing FILE.
  auto body = [](Args& args) {
    args.flag("--json", "json");
    args.positional("FILE", "file");
    args.done();
    return 0;
  };
  const auto message = [&](std::vector<std::string> words) {
    std::vector<char*> argv;
    for (auto& w : words)
      argv.push_back(w.data());
    Args args("prog", int(argv.size()), argv.data());
    try {
      body(args);
    } catch (const UsageError& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_EQ(message({"prog", "--bogus"}), "unknown option --bogus (see --help)");
  EXPECT_EQ(message({"prog", "--json"}), "missing FILE (see --help)");
  EXPECT_EQ(message({"prog", "--json", "f.vpk"}), "no error");
}

TEST(Args, ExceptionsMapToExitCodes) {
  EXPECT_EQ(run_args({"p"}, [](Args&) -> int { throw IoError("x"); }), 3);
  EXPECT_EQ(run_args({"p"}, [](Args&) -> int { throw FormatError("x"); }), 4);
  EXPECT_EQ(run_args({"p"}, [](Args&) -> int { throw ConfigError("x"); }), 5);
  EXPECT_EQ(run_args({"p"}, [](Args&) -> int { throw InputError("x"); }), 6);
  EXPECT_EQ(run_args({"p"}, [](Args&) -> int { throw std::runtime_error("x"); }), 1);
}

TEST(SliceRange, ParsesAndClamps) {
  auto r = parse_slice_range("3:10", 100);
  EXPECT_EQ(r.first, 3);
  EXPECT_EQ(r.last, 10);
  r = parse_slice_range(":", 50);
  EXPECT_EQ(r.first, 0);
  EXPECT_EQ(r.last, 50);
  r = parse_slice_range("40:", 50);
  EXPECT_EQ(r.size(), 10);
  r = parse_slice_range("0:1000", 50);
  EXPECT_EQ(r.last, 50);
  EXPECT_THROW(parse_slice_range("7", 50), UsageError);
  EXPECT_THROW(parse_slice_range("9:3", 50), UsageError);
  EXPECT_THROW(parse_slice_range("a:3", 50), UsageError);
  EXPECT_THROW(parse_slice_range("-2:3", 50), UsageError);
}

TEST(ParallelFor, VisitsEveryIndexOnceAndPropagatesFirstError) {
  std::vector<std::atomic<int>> hits(1000);
  parallel_for(1000, 4, [&](std::int64_t i) { hits[std::size_t(i)]++; });
  for (auto& h : hits)
    EXPECT_EQ(h.load(), 1);
  EXPECT_THROW(parallel_for(100, 3,
                            [](std::int64_t i) {
                              if (i == 37) throw InputError("slice 37 is bad");
                            }),
               InputError);
  parallel_for(0, 4, [](std::int64_t) { FAIL() << "no work for count 0"; });
}

TEST(Hash, XxHash64KnownVectors) {
  // Reference values from the xxHash specification (seed 0).
  EXPECT_EQ(xxh64("", 0), 0xEF46DB3751D8E999ULL);
  EXPECT_EQ(hex64(0xEF46DB3751D8E999ULL), "ef46db3751d8e999");
  TempDir dir;
  write_file_atomic(dir / "h", "vispack");
  EXPECT_EQ(xxh64_file(dir / "h"), xxh64("vispack", 7));
}

TEST(Hash, StreamOfPiecesEqualsTheWhole) {
  std::string bytes(100000, '\0');
  for (std::size_t i = 0; i < bytes.size(); ++i)
    bytes[i] = char((i * 131 + i / 7) & 0xff);
  Xxh64Stream none;
  EXPECT_EQ(none.digest(), xxh64("", 0));
  Xxh64Stream pieces;
  std::size_t at = 0;
  for (std::size_t n : {0, 1, 31, 32, 33, 4096, 50000}) {  // sizes across xxHash's 32-byte stripes
    pieces.update(bytes.data() + at, n);
    at += n;
  }
  pieces.update(bytes.data() + at, bytes.size() - at);
  EXPECT_EQ(pieces.digest(), xxh64(bytes.data(), bytes.size()));
  EXPECT_NE(pieces.digest(), xxh64(bytes.data(), bytes.size() - 1));
}

// Golden tests of `vispack-info --verify --deep`: one case per numbered finding kind
// (format/FINDINGS.md) under tests/cli/vispack-info/<case>/. Each case folder holds `args` (the
// command line after the program, run in a scratch folder holding volume.vpk), `exit_code`,
// `stdout` and `stderr` (exact). This test writes a sound volume, corrupts it the way the case
// is named (the table below), runs the tool and compares all three.
// To rewrite the expected files after a deliberate change: VISPACK_UPDATE_GOLDEN=1 ctest -R golden
// (then review the diff).
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <algorithm>
#include <cstdlib>
#include <functional>
#include <map>
#include <set>

#include "format_test_util.h"

using namespace vispack::format;
using namespace vispack::format::testing;

namespace {

const std::filesystem::path kGolden =
    std::filesystem::path(VISPACK_SOURCE_DIR) / "tests" / "cli" / "vispack-info";
const std::string kInfo = std::string(VISPACK_BIN_DIR) + "/vispack-info";

using Bytes = std::vector<std::uint8_t>;

// The sound file every case starts from: raw bricks (compression off), so the sizes and
// checksums in the expected output do not depend on the zstd version.
const Bytes& sound_file() {
  static const Bytes bytes = [] {
    Volume v = make_volume({24, 20, 18}, 9);
    WriterOptions o = options_for(v, 8);
    o.compress = false;
    const std::string path = temp_path("golden_sound.vpk");
    write(path, v, o);
    return read_bytes(path);
  }();
  return bytes;
}

const Reader& sound_reader() {
  static const std::string path = [] {
    std::string p = temp_path("golden_sound_reader.vpk");
    write_bytes(p, sound_file());
    return p;
  }();
  static const Reader reader = Reader::open(path);
  return reader;
}

// Index position of the first brick of `channel` at `level` with codec `codec` (and, for a
// label channel, at least `min_labels` IDs in its set).
std::size_t find_brick(int level, const std::string& channel, Codec codec,
                       std::uint32_t min_labels = 0) {
  const Reader& r = sound_reader();
  const int c = r.channel_index(channel);
  for (std::size_t k = 0; k < r.bricks().size(); ++k) {
    const BrickInfo& b = r.bricks()[k];
    if (b.level == level && b.channel == c && b.codec == codec && b.label_count >= min_labels)
      return k;
  }
  ADD_FAILURE() << "no " << codec_name(codec) << " brick of " << channel << " at level " << level;
  return 0;
}

std::uint8_t* entry(Parts& p, std::size_t k) {
  return p.index.data() + 64 * k;
}

// How each case corrupts the sound file (the case folder's name is the key).
const std::map<std::string, std::function<Bytes(const Bytes&)>>& cases() {
  static const std::map<std::string, std::function<Bytes(const Bytes&)>> table = {
      {"00-sound", [](const Bytes& f) { return f; }},
      {"01-bad-magic",
       [](const Bytes& f) {
         Bytes b = f;
         b[0] = 'X';
         return b;
       }},
      {"02-newer-version",
       [](const Bytes& f) {
         Bytes b = f;
         b[8] = 2;  // version_major 2
         return b;
       }},
      {"03-truncated", [](const Bytes& f) { return Bytes(f.begin(), f.end() - 100); }},
      {"04-header-field",
       [](const Bytes& f) {
         Bytes b = f;
         set_u32(b, 104, 1);  // flags
         rechecksum(b);
         return b;
       }},
      {"05-table-checksum",
       [](const Bytes& f) {
         Bytes b = f;
         b[get_u64(b, 40) + 20] ^= 0x01;  // a metadata byte, checksum left as it was
         return b;
       }},
      {"06-metadata",
       [](const Bytes& f) {
         Parts p = split(f);
         nlohmann::json m = nlohmann::json::parse(p.meta);
         m["spacing_mm"][1] = -0.5;
         p.meta = m.dump();
         return assemble(p);
       }},
      {"07-index-entry",
       [](const Bytes& f) {
         Parts p = split(f);
         entry(p, find_brick(0, "ct", Codec::kRaw))[15] = 1;  // reserved byte
         return assemble(p);
       }},
      {"08-payload-checksum",
       [](const Bytes& f) {
         // Two bricks: one finding each.
         Bytes b = f;
         const Reader& r = sound_reader();
         b[r.bricks()[find_brick(0, "rgba", Codec::kRaw)].offset + 100] ^= 0x40;
         b[r.bricks()[find_brick(1, "labels", Codec::kRaw)].offset] ^= 0x01;
         return b;
       }},
      {"09-payload-decode",
       [](const Bytes& f) {
         // A raw ct brick turned into a 16-byte zstd payload that is not a valid frame, with a
         // matching checksum: only decoding finds it.
         Parts p = split(f);
         const std::size_t k = find_brick(0, "ct", Codec::kRaw);
         const BrickInfo& b = sound_reader().bricks()[k];
         std::uint8_t* payload = p.payload.data() + (b.offset - 4096);
         std::memset(payload, 0, std::size_t(b.stored_size));
         const std::uint8_t frame[16] = {0x28, 0xB5, 0x2F, 0xFD, 0xFF, 0xFF, 0xFF, 0xFF,
                                         0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF};
         std::memcpy(payload, frame, 16);
         std::uint8_t* e = entry(p, k);
         e[14] = 2;  // zstd
         const std::uint64_t size = 16, sum = vispack::xxh64(frame, 16);
         std::memcpy(e + 24, &size, 8);
         std::memcpy(e + 32, &sum, 8);
         return assemble(p);
       }},
      {"10-brick-range",
       [](const Bytes& f) {
         Parts p = split(f);
         std::uint8_t* e = entry(p, find_brick(0, "ct", Codec::kRaw));
         std::int16_t max;
         std::memcpy(&max, e + 48, 2);
         max = std::int16_t(max + 1);  // still >= min: only decoding finds it
         std::memcpy(e + 48, &max, 2);
         return assemble(p);
       }},
      {"11-brick-labels",
       [](const Bytes& f) {
         // A middle ID of a label set replaced by an absent ID between its neighbours: the set
         // stays ascending with the same min and max, so only decoding finds it.
         Parts p = split(f);
         const Reader& r = sound_reader();
         for (const BrickInfo& b : r.bricks()) {
           if (b.label_count < 3) continue;
           const auto ids = r.brick_labels(b);
           for (std::size_t i = 1; i + 1 < ids.size(); ++i) {
             for (std::uint32_t id = ids[i - 1] + 1; id < ids[i + 1]; ++id) {
               if (id == ids[i]) continue;
               const std::uint32_t at = b.label_first + std::uint32_t(i);
               std::memcpy(p.labels.data() + 4 * at, &id, 4);
               return assemble(p);
             }
           }
         }
         ADD_FAILURE() << "no label set with a gap";
         return f;
       }},
      {"12-padding",
       [](const Bytes& f) {
         // A byte after a payload (names the brick) and a byte of the header padding.
         Bytes b = f;
         const BrickInfo& brick = sound_reader().bricks()[find_brick(0, "labels", Codec::kRaw)];
         b[brick.offset + brick.stored_size + 7] = 0x5A;
         b[300] = 0x01;
         return b;
       }},
  };
  return table;
}

struct Result {
  int code = -1;
  std::string out, err;
};

Result run_in(const std::filesystem::path& dir, const std::string& args) {
  const std::string command =
      "cd '" + dir.string() + "' && '" + kInfo + "' " + args + " >stdout.txt 2>stderr.txt";
  const int status = std::system(command.c_str());
  Result r;
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  r.out = vispack::read_file((dir / "stdout.txt").string());
  r.err = vispack::read_file((dir / "stderr.txt").string());
  return r;
}

std::string trim(std::string s) {
  while (!s.empty() && (s.back() == '\n' || s.back() == ' '))
    s.pop_back();
  return s;
}

class InfoGolden : public ::testing::TestWithParam<std::string> {};

TEST_P(InfoGolden, MatchesExitCodeStdoutAndStderr) {
  const std::string name = GetParam();
  const std::filesystem::path golden = kGolden / name;
  ASSERT_TRUE(std::filesystem::is_directory(golden)) << golden;
  const std::filesystem::path dir = temp_path("golden_" + name);
  std::filesystem::create_directories(dir);
  write_bytes((dir / "volume.vpk").string(), cases().at(name)(sound_file()));
  const std::string args = trim(vispack::read_file((golden / "args").string()));
  const Result r = run_in(dir, args);
  if (std::getenv("VISPACK_UPDATE_GOLDEN")) {
    vispack::write_file_atomic((golden / "exit_code").string(), std::to_string(r.code) + "\n");
    vispack::write_file_atomic((golden / "stdout").string(), r.out);
    vispack::write_file_atomic((golden / "stderr").string(), r.err);
    GTEST_SKIP() << "rewrote " << golden;
  }
  EXPECT_EQ(std::to_string(r.code), trim(vispack::read_file((golden / "exit_code").string())))
      << r.err;
  EXPECT_EQ(r.out, vispack::read_file((golden / "stdout").string()));
  EXPECT_EQ(r.err, vispack::read_file((golden / "stderr").string()));
}

std::vector<std::string> case_names() {
  std::vector<std::string> names;
  for (const auto& [name, corrupt] : cases())
    names.push_back(name);
  return names;
}

INSTANTIATE_TEST_SUITE_P(Cases, InfoGolden, ::testing::ValuesIn(case_names()),
                         [](const auto& info) {
                           std::string n = info.param;
                           std::replace(n.begin(), n.end(), '-', '_');
                           return n;
                         });

TEST(InfoGoldenSet, EveryFolderHasACaseAndEveryFindingKindHasOne) {
  std::set<std::string> folders;
  for (const auto& e : std::filesystem::directory_iterator(kGolden))
    if (e.is_directory()) folders.insert(e.path().filename().string());
  std::set<std::string> named;
  for (const auto& [name, corrupt] : cases())
    named.insert(name);
  EXPECT_EQ(folders, named) << "a folder without a corruption, or a corruption without a folder";
  // Kinds 1..12 each have a case whose stderr holds that finding.
  for (int kind = 1; kind <= 12; ++kind) {
    bool found = false;
    for (const auto& name : named) {
      const std::string err = vispack::read_file((kGolden / name / "stderr").string());
      found |=
          err.find("vispack-info: finding " + std::to_string(kind) + ": ") != std::string::npos;
    }
    EXPECT_TRUE(found) << "no golden case shows finding " << kind;
  }
}

}  // namespace

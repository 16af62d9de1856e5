// Faults and bad input (docs/RELIABILITY.md): each case runs vispack-run on a copy of the tiny
// phantom whose pipeline already ran once, injects one fault, and checks
//  - the exit code (README table: 3 I/O, 4 invalid file, 5 config, 6 input),
//  - that stderr is exactly one line "vispack-run: error: ..." naming the culprit,
//  - that every output of the earlier run is still there, byte for byte, and no temporary is left.
// docs/RELIABILITY.md lists every case with the message it prints.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <sstream>
#include <thread>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/hash.h"
#include "vispack/format/reader.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace fs = std::filesystem;
using vispack::test::bin;
using vispack::test::run_command;
using vispack::test::TempDir;

namespace {

struct Result {
  int rc = -1;
  std::string err;  // stderr only
};

// Content hash of every regular file under `dir`, by path relative to `dir`.
std::map<std::string, std::uint64_t> snapshot(const fs::path& dir) {
  std::map<std::string, std::uint64_t> out;
  if (!fs::exists(dir)) return out;
  for (const auto& e : fs::recursive_directory_iterator(dir))
    if (e.is_regular_file())
      out[fs::relative(e.path(), dir).string()] = vispack::xxh64_file(e.path().string());
  return out;
}

std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);)
    if (!line.empty()) out.push_back(line);
  return out;
}

class Faults : public ::testing::Test {
 protected:
  // One tiny phantom, run through the whole pipeline once; every test works on a copy. ctest
  // runs each test in its own process, so the base is cached beside the binaries, keyed by the
  // tools' modification times, and built in a temporary folder renamed into place (two test
  // processes racing both succeed; one rename wins).
  static void SetUpTestSuite() {
    std::error_code ec;
    std::string key;
    for (const char* tool : {"vispack-run", "vispack-phantom"})
      key += std::to_string(fs::last_write_time(bin(tool), ec).time_since_epoch().count());
    base_ = fs::path(VISPACK_BIN_DIR).parent_path() / "test-cache" /
            ("faults-" + vispack::hex64(vispack::xxh64(key.data(), key.size())));
    if (fs::exists(base_ / "ph/out/volume.vpk")) return;
    fs::create_directories(base_.parent_path());
    const fs::path build = base_.string() + ".tmp-" + std::to_string(::getpid());
    fs::remove_all(build, ec);
    const std::string ph = (build / "ph").string();
    ASSERT_EQ(run_command(bin("vispack-phantom") + " --preset tiny --seed 3 --no-defects --quiet " +
                          "--threads 2 --out " + ph),
              0);
    fs::remove_all(ph + "/truth");
    std::string out;
    ASSERT_EQ(run_command(bin("vispack-run") + " " + ph + "/config.json --quiet --threads 2", &out),
              0)
        << out;
    fs::rename(build, base_, ec);  // fails harmlessly if another process won
    if (ec) fs::remove_all(build, ec);
    ASSERT_TRUE(fs::exists(base_ / "ph/out/volume.vpk")) << base_;
  }

  void SetUp() override {
    dir_ = std::make_unique<TempDir>("vispack-fault");
    root_ = *dir_ / "ph";
    fs::copy(base_ / "ph", root_, fs::copy_options::recursive);
    before_work_ = snapshot(root_ + "/work");
    before_out_ = snapshot(root_ + "/out");
    ASSERT_FALSE(before_out_.empty());
  }

  std::string path(const std::string& rel) const { return root_ + "/" + rel; }
  std::string config() const { return path("config.json"); }

  // Runs `prefix vispack-run config.json --quiet args` and keeps stderr only.
  Result run(const std::string& args, const std::string& prefix = "") const {
    Result r;
    r.rc = run_command("(" + prefix + bin("vispack-run") + " " + config() +
                           " --quiet --threads 2 " + args + " 2>&1 >/dev/null)",
                       &r.err);
    return r;
  }

  // Runs vispack-run like run(), with one thread and VISPACK_TEST_PAUSE=<point>: when the run
  // stops at `point`, calls `action`, then lets it go on. Fails if the point is never reached.
  template <class F>
  Result run_paused(const std::string& args, const std::string& point, F action) const {
    const std::string flag = *dir_ / "paused";
    Result r;
    std::atomic<bool> finished{false};
    std::thread runner([&] {
      r.rc = run_command("(VISPACK_TEST_PAUSE='" + point + "@" + flag + "' " + bin("vispack-run") +
                             " " + config() + " --quiet --threads 1 " + args + " 2>&1 >/dev/null)",
                         &r.err);
      finished = true;
    });
    bool reached = false;
    for (int i = 0; i < 60000 && !reached; ++i) {
      const bool done = finished;  // read before looking for the flag
      reached = fs::exists(flag);
      if (!reached && done) break;  // finished without pausing
      if (!reached) std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    if (reached) {
      action();
      fs::remove(flag);
    }
    runner.join();
    EXPECT_TRUE(reached) << "vispack-run never reached " << point << "; exit " << r.rc << ": "
                         << r.err;
    return r;
  }

  void expect_no_temporaries() const {
    for (const auto& dir : {"work", "out"})
      for (const auto& [rel, hash] : snapshot(path(dir)))
        EXPECT_EQ(rel.find(".tmp-"), std::string::npos) << dir << "/" << rel << " left behind";
  }

  // Edits config.json through `edit`.
  template <class F>
  void edit_config(F edit) const {
    nlohmann::json j = nlohmann::json::parse(vispack::read_file(config()));
    edit(j);
    std::ofstream(config()) << j.dump(2);
  }

  // Exit code `rc`, one stderr line "vispack-run: error: ..." that contains every `names`.
  static void expect_error(const Result& r, int rc, const std::vector<std::string>& names) {
    EXPECT_EQ(r.rc, rc) << r.err;
    std::cout << "[ message  ] exit " << r.rc << ": " << r.err;  // for docs/RELIABILITY.md
    const auto lines = lines_of(r.err);
    ASSERT_EQ(lines.size(), 1u) << "not one line:\n" << r.err;
    EXPECT_EQ(lines[0].rfind("vispack-run: error: ", 0), 0u) << lines[0];
    for (const auto& name : names)
      EXPECT_NE(lines[0].find(name), std::string::npos)
          << "'" << name << "' not named: " << lines[0];
  }

  // Every output of the first run is still there: products (images, transforms.json, the
  // packed and VDB files) with the same bytes; bookkeeping (manifest.json, report.json,
  // register/pairs/*.json, which record absolute input paths and so legitimately change in a
  // copied tree) still complete JSON; the pairs' QC pictures (register/pairs/*.png) are products.
  // No temporary is left.
  void expect_earlier_outputs_intact() const {
    for (const auto& [dir, before] : {std::pair{"work", &before_work_}, {"out", &before_out_}}) {
      const auto now = snapshot(path(dir));
      for (const auto& [rel, hash] : *before) {
        auto it = now.find(rel);
        const std::string name = fs::path(rel).filename().string();
        const bool bookkeeping =
            name == "manifest.json" || name == "report.json" ||
            (rel.find("pairs/") != std::string::npos && fs::path(rel).extension() == ".json");
        if (it == now.end()) {
          ADD_FAILURE() << dir << "/" << rel << " disappeared";
        } else if (bookkeeping) {
          EXPECT_TRUE(
              nlohmann::json::accept(vispack::read_file(path(std::string(dir) + "/" + rel))))
              << dir << "/" << rel << " is not complete JSON";
        } else {
          EXPECT_EQ(it->second, hash) << dir << "/" << rel << " changed";
        }
      }
      for (const auto& [rel, hash] : now)
        EXPECT_EQ(rel.find(".tmp-"), std::string::npos) << dir << "/" << rel << " left behind";
    }
  }

  // Makes the folders `read_only` (relative to the tree) unwritable for the stage, and returns
  // the command prefix that runs it so. Root ignores permissions, so as root the stage runs as
  // user nobody (setpriv) on a tree everyone can read and only root can write, apart from the
  // folders not named; as any other user those folders lose their write permission (given back
  // in TearDown so the folder can be removed).
  std::string read_only_for_the_stage(const std::vector<std::string>& read_only) {
    if (::geteuid() == 0) {
      if (run_command("command -v setpriv") != 0) {
        ADD_FAILURE() << "running as root needs setpriv (util-linux) to run the stage as nobody";
        return "";
      }
      ::chmod(dir_->path().c_str(), 0755);  // TempDir is mode 0700
      EXPECT_EQ(run_command("chmod -R a+rX,go-w " + root_), 0);
      for (const char* folder : {"work", "out"}) {
        if (std::find(read_only.begin(), read_only.end(), folder) == read_only.end()) {
          EXPECT_EQ(run_command("chmod -R a+w " + path(folder)), 0);
        }
      }
      return "setpriv --reuid=65534 --regid=65534 --clear-groups ";
    }
    for (const auto& folder : read_only)
      EXPECT_EQ(run_command("chmod -R a-w " + path(folder)), 0);
    made_read_only_ = true;
    return "";
  }

  void TearDown() override {
    if (made_read_only_) run_command("chmod -R u+w " + root_);
  }

  bool made_read_only_ = false;
  static fs::path base_;
  std::unique_ptr<TempDir> dir_;
  std::string root_;
  std::map<std::string, std::uint64_t> before_work_, before_out_;
};

fs::path Faults::base_;

// ---- disk full and unwritable output ----

TEST_F(Faults, DiskFullWhilePackingKeepsThePreviousVolume) {
  // RLIMIT_FSIZE of 20 KiB (ulimit -f counts 1 KiB blocks); SIGXFSZ ignored so write() fails with
  // EFBIG as on a full disk instead of killing the process. The packed file is ~600 KB.
  Result r =
      run("--force --from pack", "bash -c 'trap \"\" XFSZ; ulimit -f 20; exec \"$0\" \"$@\"' ");
  expect_error(r, 3, {path("out/volume.vpk"), "write failed", "File too large"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, DiskFullInTheFirstStage) {
  Result r = run("--force", "bash -c 'trap \"\" XFSZ; ulimit -f 2; exec \"$0\" \"$@\"' ");
  expect_error(r, 3, {path("work/register/"), "File too large"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, RealFullFilesystem) {
  // A 200 KiB tmpfs as the output folder: ENOSPC. As root, mounted here; otherwise inside a user
  // and mount namespace (unshare -rm), where an unprivileged user may mount a tmpfs. Skipped only
  // where the kernel allows neither.
  const std::string mnt = path("small");
  fs::create_directories(mnt);
  const std::string mount = "mount -t tmpfs -o size=200k tmpfs " + mnt;
  std::string prefix;
  const bool mounted = ::geteuid() == 0 && run_command(mount) == 0;
  if (!mounted) {
    if (run_command("unshare -rm sh -c '" + mount + "'") != 0)
      GTEST_SKIP() << "cannot mount a tmpfs here, neither as root nor in a user namespace";
    prefix = "unshare -rm sh -c '" + mount + " && exec \"$0\" \"$@\"' ";
  }
  edit_config([](nlohmann::json& j) { j["output"] = "small/volume.vpk"; });
  Result r = run("", prefix);
  if (mounted) run_command("umount " + mnt);
  expect_error(r, 3, {path("small/volume.vpk"), "No space left on device"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ReadOnlyOutputFolder) {
  Result r = run("--force --from pack", read_only_for_the_stage({"out"}));
  expect_error(r, 3, {path("out/volume.vpk"), "Permission denied"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ReadOnlyWorkFolder) {
  Result r = run("--force", read_only_for_the_stage({"work", "out"}));
  // The run's lock file (work_lock.h) is the first thing it writes into the work folder.
  expect_error(r, 3, {path("work/.vispack.lock"), "Permission denied"});
  expect_earlier_outputs_intact();
}

// ---- slices that vanish, change or are corrupt ----

TEST_F(Faults, SliceDisappearsBetweenStages) {
  fs::remove(path("rgb/rgb_0023.png"));
  Result r = run("--from mask");
  expect_error(r, 6,
               {path("rgb/rgb_0023.png"), path("work/register/transforms.json"), "24 slices",
                "the stack has 23"});
  expect_earlier_outputs_intact();
}

// The slice is deleted at a moment the test controls: vispack-run (VISPACK_TEST_PAUSE) stops at
// the named point and waits until the deletion is done. With one thread the order of slices in a
// stage is fixed, so each case has one right answer.
TEST_F(Faults, SliceDisappearsBeforeAStageStarts) {
  // Register read all 24 slices; the slice goes before mask starts. Mask finds the stack one
  // short of transforms.json and must name the slice, not only transforms.json.
  const std::string victim = path("rgb/rgb_0023.png");
  Result r = run_paused("--force", "before:mask", [&] { fs::remove(victim); });
  expect_error(r, 6, {victim, "gone", "24 slices", "the stack has 23", "rerun vispack-register"});
  expect_no_temporaries();
}

TEST_F(Faults, SliceDisappearsMidStage) {
  // Register has written QC overlay 5 (of 24, one thread, in order) when the last slice goes.
  // Register read every slice once, in its pair phase, and draws the overlays from what it kept
  // (docs/ARCHITECTURE.md, 'Work folder layout'), so it finishes; mask finds the stack one short of
  // transforms.json and names the slice.
  const std::string victim = path("rgb/rgb_0023.png");
  Result r = run_paused("--force", "done:register:5", [&] { fs::remove(victim); });
  expect_error(r, 6, {victim, "gone", "24 slices", "the stack has 23", "rerun vispack-register"});
  expect_no_temporaries();
  // The rerun starts from the 23 slices left and builds a consistent volume.
  Result again = run("");
  ASSERT_EQ(again.rc, 0) << again.err;
  auto reader = vispack::format::Reader::open(path("out/volume.vpk"));
  EXPECT_EQ(reader.dims(0)[2], 23);
}

TEST_F(Faults, SliceDisappearsWhileMasking) {
  // Mask rebuilds the registered colour from the colour folder (docs/ARCHITECTURE.md, 'Work folder
  // layout': no full-size copies in the work folder), so it names the slice when it reaches it.
  const std::string victim = path("rgb/rgb_0023.png");
  Result r = run_paused("--force", "done:mask:5", [&] { fs::remove(victim); });
  expect_error(r, 6, {victim, "does not exist"});
  expect_no_temporaries();
}

TEST_F(Faults, SliceChangesSize) {
  cv::Mat m = vispack::pipeline::read_slice(path("rgb/rgb_0005.png"));
  vispack::pipeline::write_image(path("rgb/rgb_0005.png"), m(cv::Rect(0, 0, 90, 60)).clone());
  Result r = run("");
  expect_error(r, 6, {path("rgb/rgb_0005.png"), "90x60", "96x64"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ZeroByteImage) {
  std::ofstream(path("rgb/rgb_0007.png"), std::ios::trunc);
  Result r = run("");
  expect_error(r, 6, {path("rgb/rgb_0007.png"), "empty"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, TruncatedPng) {
  std::string png = vispack::read_file(path("rgb/rgb_0009.png"));
  ASSERT_GT(png.size(), 2000u);
  vispack::write_file_atomic(path("rgb/rgb_0009.png"), png.substr(0, png.size() / 2));
  Result r = run("");
  expect_error(r, 6, {path("rgb/rgb_0009.png"), "PNG is truncated"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, TruncatedCtSlice) {
  std::string png = vispack::read_file(path("ct/ct_0004.png"));
  vispack::write_file_atomic(path("ct/ct_0004.png"), png.substr(0, png.size() - 100));
  Result r = run("");
  expect_error(r, 6, {path("ct/ct_0004.png"), "PNG is truncated"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, SixteenBitRawWhereEightBitIsDeclared) {
  // A raw colour stack (rgb.raw declares 8 bits); one slice written with 16-bit samples.
  const std::string raw = *dir_ / "raw";
  ASSERT_EQ(run_command(bin("vispack-phantom") +
                        " --preset tiny --slices 4 --rgb-raw --no-defects --quiet --out " + raw),
            0);
  nlohmann::json j = nlohmann::json::parse(vispack::read_file(raw + "/config.json"));
  ASSERT_EQ(j["rgb"]["raw"]["bits"], 8);
  std::vector<std::string> slices;
  for (const auto& e : fs::directory_iterator(raw + "/rgb"))
    slices.push_back(e.path().string());
  std::sort(slices.begin(), slices.end());
  ASSERT_EQ(slices.size(), 4u);
  const std::string slice = slices[2];
  std::string bytes = vispack::read_file(slice);
  std::string wide;
  for (char c : bytes)
    wide += {c, '\0'};  // little-endian 16-bit samples
  vispack::write_file_atomic(slice, wide);
  Result r;
  r.rc = run_command("(" + bin("vispack-run") + " " + raw + "/config.json --quiet 2>&1 >/dev/null)",
                     &r.err);
  expect_error(r, 6, {slice, std::to_string(bytes.size()), std::to_string(wide.size())});
}

TEST_F(Faults, SixteenBitPngColourSliceIsConverted) {
  // A 16-bit PNG among 8-bit ones is not an error: it is scaled to 8 bits (255/65535).
  cv::Mat m = vispack::pipeline::read_slice(path("rgb/rgb_0006.png"));
  cv::Mat wide;
  m.convertTo(wide, CV_16UC3, 65535.0 / 255.0);
  vispack::pipeline::write_image(path("rgb/rgb_0006.png"), wide);
  edit_config([](nlohmann::json& j) { j["work"]["write_registered"] = true; });
  Result r = run("");
  EXPECT_EQ(r.rc, 0) << r.err;
  cv::Mat registered = vispack::pipeline::read_slice(path("work/register/registered/rgb_0006.png"));
  EXPECT_EQ(registered.type(), CV_8UC3);
}

TEST_F(Faults, CtMissingInsideTheStack) {
  fs::remove(path("ct/ct_0010.png"));
  Result r = run("");
  expect_error(r, 6, {path("ct"), "CT slice 10 is missing", "ct_0009.png", "ct_0011.png"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, CtMissingAtTheEndGivesColourOnlyMasks) {
  // CT k lies on colour k; colour slices beyond the CT stack get a mask from colour alone, and
  // the mask report counts them.
  fs::remove(path("ct/ct_0022.png"));
  fs::remove(path("ct/ct_0023.png"));
  Result r = run("");
  ASSERT_EQ(r.rc, 0) << r.err;
  auto report = nlohmann::json::parse(vispack::read_file(path("work/mask/report.json")));
  EXPECT_EQ(report["quality"]["colour_only_slices"], 2);
}

// ---- bad configs ----

TEST_F(Faults, ConfigWrongType) {
  edit_config([](nlohmann::json& j) { j["pack"]["brick_edge"] = "64"; });
  Result r = run("");
  expect_error(r, 5, {config(), "pack.brick_edge", "must be an integer"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ConfigUnknownKey) {
  edit_config([](nlohmann::json& j) { j["mask"]["hu_treshold"] = -400; });
  Result r = run("");
  expect_error(r, 5, {config(), "mask.hu_treshold", "unknown key"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ConfigFolderDoesNotExist) {
  edit_config([](nlohmann::json& j) { j["ct"]["dir"] = "no-such-ct"; });
  Result r = run("");
  expect_error(r, 5, {config(), "ct.dir", path("no-such-ct"), "does not exist"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ConfigPaletteDoesNotExist) {
  edit_config([](nlohmann::json& j) { j["seg"]["palette"] = "nope.json"; });
  Result r = run("");
  expect_error(r, 5, {config(), "seg.palette", "nope.json"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ConfigNotJson) {
  std::ofstream(config(), std::ios::app) << "}";
  Result r = run("");
  expect_error(r, 5, {config(), "not valid JSON"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ConfigNumberOverflow) {
  // Found by fuzz_config: a number beyond double range escaped as std::out_of_range (exit 1).
  std::string text = vispack::read_file(config());
  text.replace(text.find("0.5,"), 4, "1E99999,");
  vispack::write_file_atomic(config(), text);
  Result r = run("");
  expect_error(r, 5, {config(), "not valid JSON", "number overflow"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, ConfigFileMissing) {
  fs::remove(config());
  Result r = run("");
  expect_error(r, 3, {config()});
}

TEST_F(Faults, OutputEqualToAnInputSlice) {
  const std::string slice = vispack::read_file(path("rgb/rgb_0000.png"));
  edit_config([](nlohmann::json& j) { j["output"] = "rgb/rgb_0000.png"; });
  Result r = run("");
  expect_error(r, 5, {config(), "output", path("rgb/rgb_0000.png"), "input slice folder"});
  EXPECT_EQ(vispack::read_file(path("rgb/rgb_0000.png")), slice);
  expect_earlier_outputs_intact();
}

TEST_F(Faults, OutputEqualToTheConfig) {
  edit_config([](nlohmann::json& j) { j["vdb_output"] = "./config.json"; });
  Result r = run("");
  expect_error(r, 5, {config(), "vdb_output", "the config file"});
  expect_earlier_outputs_intact();
}

TEST_F(Faults, WorkFolderIsAnInputFolder) {
  edit_config([](nlohmann::json& j) { j["work_dir"] = "seg"; });
  Result r = run("");
  expect_error(r, 5, {config(), "work_dir", path("seg")});
  expect_earlier_outputs_intact();
}

}  // namespace

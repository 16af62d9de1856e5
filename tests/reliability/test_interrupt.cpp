// Interruption (docs/RELIABILITY.md): each stage is killed with SIGKILL in the middle of its work,
// at moments the test controls (VISPACK_TEST_PAUSE stops the stage after it wrote slice k, or for
// pack after it handed slice k to the writer, and the kill lands while it waits), and besides at
// seeded random moments that may land anywhere, inside a write too. After every kill, no output
// path may hold a partial file (a file is either absent, a temporary "*.tmp-*" name, or complete: a
// PNG that decodes, JSON that parses, a packed file that verifies). After the rerun, every output
// equals the uninterrupted run's and no temporary file is left behind.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <map>
#include <random>
#include <thread>

#include <nlohmann/json.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/format/reader.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace fs = std::filesystem;
using vispack::test::bin;
using vispack::test::run_command;
using vispack::test::TempDir;

namespace {

const std::vector<std::string> kStages = {"register", "mask", "labels", "pack", "vdb"};

bool is_temp(const fs::path& p) {
  return p.filename().string().find(".tmp-") != std::string::npos;
}

// Every regular file under `dir` (recursively) by path relative to `dir`.
std::map<std::string, fs::path> files_under(const fs::path& dir) {
  std::map<std::string, fs::path> out;
  if (!fs::exists(dir)) return out;
  for (const auto& e : fs::recursive_directory_iterator(dir))
    if (e.is_regular_file()) out[fs::relative(e.path(), dir).string()] = e.path();
  return out;
}

// Checks that a file at a final (non-temporary) output path is complete. Returns "" if it is,
// else why not.
std::string completeness_problem(const fs::path& p) {
  std::string ext = p.extension().string();
  try {
    if (ext == ".png" || ext == ".tif") {
      cv::Mat m = vispack::pipeline::read_slice(p.string());
      if (m.empty()) return "empty image";
    } else if (ext == ".json") {
      if (!nlohmann::json::accept(vispack::read_file(p.string()))) return "not complete JSON";
    } else if (ext == ".vpk") {
      auto reader = vispack::format::Reader::open(p.string());
      auto result = reader.verify();
      if (!result.ok) return result.message;
    } else if (ext == ".vdb") {
      std::string out;
      if (run_command("vdb_print " + p.string(), &out) != 0) return "vdb_print failed: " + out;
    }
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

// Starts `argv` as a child process with its output discarded; returns its pid. `pause`, when
// not empty, is the child's VISPACK_TEST_PAUSE.
pid_t spawn(const std::vector<std::string>& args, const std::string& pause = "") {
  std::fflush(stdout);  // or the child's freopen flushes our pending output a second time
  std::fflush(stderr);
  pid_t pid = ::fork();
  if (pid == 0) {
    std::vector<char*> argv;
    for (const auto& a : args)
      argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    FILE* null_out = std::freopen("/dev/null", "w", stdout);
    FILE* null_err = std::freopen("/dev/null", "w", stderr);
    (void)null_out;
    (void)null_err;
    if (!pause.empty()) ::setenv("VISPACK_TEST_PAUSE", pause.c_str(), 1);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  return pid;
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

class Interrupt : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    root_ = new TempDir("vispack-interrupt");
    std::string out;
    // The tiny phantom with defects (black + duplicate slice) so every code path runs.
    ASSERT_EQ(run_command(bin("vispack-phantom") + " --preset tiny --seed 11 --defects --out " +
                              (*root_ / "ref"),
                          &out),
              0)
        << out;
    fs::copy(*root_ / "ref", *root_ / "int", fs::copy_options::recursive);
    // The uninterrupted reference run, stage by stage, timing each stage.
    for (const auto& stage : kStages) {
      auto t0 = std::chrono::steady_clock::now();
      ASSERT_EQ(
          run_command(bin("vispack-" + stage) + " --quiet --config " + (*root_ / "ref/config.json"),
                      &out),
          0)
          << stage << ": " << out;
      stage_seconds_[stage] = seconds_since(t0);
    }
  }
  static void TearDownTestSuite() {
    delete root_;
    root_ = nullptr;
  }

  // The places a stage writes: its work folder plus, for pack and vdb, the output files.
  static std::vector<fs::path> output_places(const std::string& tree, const std::string& stage) {
    auto config = nlohmann::json::parse(vispack::read_file(*root_ / (tree + "/config.json")));
    fs::path base = *root_ / tree;
    std::vector<fs::path> places = {base / config.value("work_dir", "work") / stage};
    if (stage == "pack") places.push_back(base / config.value("output", "out/volume.vpk"));
    if (stage == "vdb") places.push_back(base / config.value("vdb_output", "out/volume.vdb"));
    return places;
  }

  static TempDir* root_;
  static std::map<std::string, double> stage_seconds_;
};
TempDir* Interrupt::root_ = nullptr;
std::map<std::string, double> Interrupt::stage_seconds_;

TEST_F(Interrupt, EveryStageResumesToTheUninterruptedResult) {
  std::mt19937_64 rng(20261122);  // seeded: the kill moments are reproducible
  std::string config = *root_ / "int/config.json";
  for (const auto& stage : kStages) {
    SCOPED_TRACE("stage " + stage);
    double t_ref = std::max(stage_seconds_[stage], 0.05);
    // Nothing partial at any final path of the stage.
    auto expect_nothing_partial = [&](const std::string& when) {
      for (const auto& place : output_places("int", stage)) {
        std::map<std::string, fs::path> files;
        if (fs::is_directory(place)) {
          files = files_under(place);
        } else if (fs::exists(place)) {
          files[place.filename().string()] = place;
        }
        for (const auto& [rel, path] : files) {
          if (is_temp(path)) continue;
          EXPECT_EQ(completeness_problem(path), "")
              << "partial file after " << when << ": " << path;
        }
      }
    };
    // 1. Kills that land mid-stage by construction: the stage stops at a pause point (slice 2
    // and slice 17 of 24 written, or handed to the pack writer), the test kills it there.
    // With --force and one thread, so each attempt has work to do in a fixed order.
    std::vector<std::string> points;
    if (stage == "pack") {
      points = {"append:pack:2", "append:pack:17"};
    } else if (stage == "vdb") {
      points = {"done:vdb:0"};  // the file is in place, the stage's bookkeeping is not
    } else {
      points = {"done:" + stage + ":2", "done:" + stage + ":17"};
    }
    for (const std::string& point : points) {
      const std::string flag = *root_ / "paused";
      pid_t pid = spawn(
          {bin("vispack-" + stage), "--quiet", "--force", "--threads", "1", "--config", config},
          point + "@" + flag);
      ASSERT_GT(pid, 0);
      bool reached = false, exited = false;
      int status = 0;
      for (int i = 0; i < 24000 && !reached && !exited; ++i) {  // up to 120 s
        reached = fs::exists(flag);
        if (!reached) exited = ::waitpid(pid, &status, WNOHANG) == pid;
        if (!reached && !exited) std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
      if (!exited) {
        ::kill(pid, SIGKILL);
        ::waitpid(pid, &status, 0);
      }
      fs::remove(flag);
      EXPECT_TRUE(reached) << stage << " never reached " << point << " (exit status " << status
                           << ")";
      EXPECT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << point;
      expect_nothing_partial("SIGKILL at " + point);
    }
    // 2. Kills at seeded random moments in [5 %, 95 %] of the reference duration: these may
    // land anywhere (start-up, inside a write, after the end) and add coverage; success does
    // not depend on where they land.
    int kills_landed = 0;
    for (int attempt = 0; attempt < 2; ++attempt) {
      double when = t_ref * std::uniform_real_distribution<double>(0.05, 0.95)(rng);
      pid_t pid = spawn({bin("vispack-" + stage), "--quiet", "--force", "--config", config});
      ASSERT_GT(pid, 0);
      std::this_thread::sleep_for(std::chrono::duration<double>(when));
      int status = 0;
      if (::waitpid(pid, &status, WNOHANG) == 0) {
        ::kill(pid, SIGKILL);
        ::waitpid(pid, &status, 0);
        ++kills_landed;
      }
      expect_nothing_partial("a random SIGKILL");
    }
    // Resume: a plain rerun (no --force) must finish the job.
    std::string out;
    ASSERT_EQ(run_command(bin("vispack-" + stage) + " --quiet --config " + config, &out), 0) << out;
    // Equal to the uninterrupted run; no temporaries left.
    auto ref_places = output_places("ref", stage);
    auto int_places = output_places("int", stage);
    for (std::size_t i = 0; i < ref_places.size(); ++i) {
      if (fs::is_directory(ref_places[i])) {
        auto ref_files = files_under(ref_places[i]);
        auto int_files = files_under(int_places[i]);
        for (const auto& [rel, path] : int_files)
          EXPECT_FALSE(is_temp(path)) << "left behind: " << path;
        for (const auto& [rel, ref_path] : ref_files) {
          // Compare the stage's products: its images and transforms.json. Reports, manifests and
          // pair records hold timings and file identities (mtimes), which differ between trees.
          std::string name = fs::path(rel).filename().string();
          bool product = fs::path(rel).extension() == ".png" || name == "transforms.json";
          if (!product) continue;
          ASSERT_TRUE(int_files.count(rel)) << "missing after resume: " << rel;
          EXPECT_EQ(vispack::read_file(ref_path.string()),
                    vispack::read_file(int_files[rel].string()))
              << "differs from the uninterrupted run: " << rel;
        }
      } else {
        // A file output: no temporary of it left beside it (the kills above left some).
        for (const auto& e : fs::directory_iterator(int_places[i].parent_path()))
          EXPECT_NE(
              e.path().filename().string().rfind(int_places[i].filename().string() + ".tmp-", 0),
              0u)
              << "left behind: " << e.path();
      }
      if (ref_places[i].extension() == ".vpk") {
        auto a = vispack::format::Reader::open(ref_places[i].string());
        auto b = vispack::format::Reader::open(int_places[i].string());
        ASSERT_EQ(a.channels().size(), b.channels().size());
        for (int c = 0; c < int(a.channels().size()); ++c)
          for (int level = 0; level < a.level_count(); ++level)
            EXPECT_EQ(a.read_level(c, level), b.read_level(c, level))
                << "channel " << c << " level " << level;
      } else if (!fs::is_directory(ref_places[i])) {
        EXPECT_EQ(completeness_problem(int_places[i]), "");
        EXPECT_GT(fs::file_size(int_places[i]), 0u);
      }
    }
    std::cout << "[ stage " << stage << " ] reference " << t_ref << " s, killed at "
              << points.size() << " pause points, " << kills_landed
              << " of 2 random kills landed while it ran\n";
  }
}

}  // namespace

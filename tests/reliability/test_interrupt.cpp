// Interruption (issue 7): each stage is killed with SIGKILL at seeded random moments while it
// runs. After every kill, no output path may hold a partial file (a file is either absent, a
// temporary "*.tmp-*" name, or complete: a PNG that decodes, JSON that parses, a packed file that
// verifies). After the rerun, every output equals the uninterrupted run's and no temporary file
// is left behind.
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
#include "vispack/pipeline/slice_io.h"

namespace fs = std::filesystem;
using vispack::test::bin;
using vispack::test::run_command;
using vispack::test::TempDir;

namespace {

const std::vector<std::string> kStages = {"register", "mask", "labels", "pack", "vdb"};

bool is_temp(const fs::path& p) { return p.filename().string().find(".tmp-") != std::string::npos; }

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
      (void)nlohmann::json::parse(vispack::read_file(p.string()));
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

// Starts `argv` as a child process with its output discarded; returns its pid.
pid_t spawn(const std::vector<std::string>& args) {
  std::fflush(stdout);  // or the child's freopen flushes our pending output a second time
  std::fflush(stderr);
  pid_t pid = ::fork();
  if (pid == 0) {
    std::vector<char*> argv;
    for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    FILE* null_out = std::freopen("/dev/null", "w", stdout);
    FILE* null_err = std::freopen("/dev/null", "w", stderr);
    (void)null_out;
    (void)null_err;
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
                              (*root_ / "ref"), &out), 0) << out;
    fs::copy(*root_ / "ref", *root_ / "int", fs::copy_options::recursive);
    // The uninterrupted reference run, stage by stage, timing each stage.
    for (const auto& stage : kStages) {
      auto t0 = std::chrono::steady_clock::now();
      ASSERT_EQ(run_command(bin("vispack-" + stage) + " --quiet --config " + (*root_ / "ref/config.json"), &out), 0)
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
    int kills_landed = 0;
    for (int attempt = 0; attempt < 4; ++attempt) {
      // Kill at a moment in [5 %, 95 %] of the reference duration. With --force so each attempt
      // has work to do (a previous attempt may have completed the stage).
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
      // Nothing partial at any final path.
      for (const auto& place : output_places("int", stage)) {
        std::map<std::string, fs::path> files;
        if (fs::is_directory(place)) {
          files = files_under(place);
        } else if (fs::exists(place)) {
          files[place.filename().string()] = place;
        }
        for (const auto& [rel, path] : files) {
          if (is_temp(path)) continue;
          EXPECT_EQ(completeness_problem(path), "") << "partial file after SIGKILL: " << path;
        }
      }
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
        for (const auto& [rel, path] : int_files) EXPECT_FALSE(is_temp(path)) << "left behind: " << path;
        for (const auto& [rel, ref_path] : ref_files) {
          // Compare the stage's products: its images and transforms.json. Reports, manifests and
          // pair records hold timings and file identities (mtimes), which differ between trees.
          std::string name = fs::path(rel).filename().string();
          bool product = fs::path(rel).extension() == ".png" || name == "transforms.json";
          if (!product) continue;
          ASSERT_TRUE(int_files.count(rel)) << "missing after resume: " << rel;
          EXPECT_EQ(vispack::read_file(ref_path.string()), vispack::read_file(int_files[rel].string()))
              << "differs from the uninterrupted run: " << rel;
        }
      } else if (ref_places[i].extension() == ".vpk") {
        auto a = vispack::format::Reader::open(ref_places[i].string());
        auto b = vispack::format::Reader::open(int_places[i].string());
        ASSERT_EQ(a.channels().size(), b.channels().size());
        for (int c = 0; c < int(a.channels().size()); ++c)
          for (int level = 0; level < a.level_count(); ++level)
            EXPECT_EQ(a.read_level(c, level), b.read_level(c, level)) << "channel " << c << " level " << level;
      } else {
        EXPECT_EQ(completeness_problem(int_places[i]), "");
        EXPECT_GT(fs::file_size(int_places[i]), 0u);
      }
    }
    // The kill moments are drawn inside the reference duration, so most land; if none did, the
    // test did not test anything for this stage.
    EXPECT_GE(kills_landed, 1) << "no kill landed while " << stage << " ran";
    std::cout << "[ stage " << stage << " ] reference " << t_ref << " s, " << kills_landed
              << " of 4 kills landed while it ran\n";
  }
}

}  // namespace

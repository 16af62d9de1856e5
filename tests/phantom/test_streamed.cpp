// The streamed phantom folder for stacks at full length (phantom.h truth_every, blocks,
// black_slices, keep_free_bytes): the files and their sizes, the male's artefacts, the truth
// sample against the whole-stack truth, scoring on the sample, and the free-space check.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/nrrd.h"
#include "vispack/phantom/phantom.h"
#include "vispack/phantom/score.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vph = vispack::phantom;
namespace fs = std::filesystem;
using vispack::test::TempDir;
using json = nlohmann::json;

namespace {

constexpr int kSlices = 16, kEvery = 5;

// male-small (384×228, CT 282²), 16 slices as NLM ships them: planar raw colour, four blocks,
// two black slices; streamed (truth of slices 0, 5, 10, 15) or with the whole-stack truth.
vph::PhantomOptions male_options(int truth_every) {
  vph::PhantomOptions o;
  o.preset = "male-small";
  o.slices = kSlices;
  o.seed = 3;
  o.rgb_raw = true;
  o.blocks = 4;
  o.black_slices = 2;
  o.truth_every = truth_every;
  o.quiet = true;
  return o;
}

std::string numbered(const std::string& dir, const std::string& stem, int k,
                     const std::string& ext) {
  char name[64];
  std::snprintf(name, sizeof name, "%s_%04d%s", stem.c_str(), k, ext.c_str());
  return dir + "/" + name;
}

struct Streamed {
  TempDir dir{"vispack-streamed-test"};
  vph::PhantomSummary summary;
  json transforms;
  Streamed() {
    summary = vph::make_phantom(dir.path(), male_options(kEvery));
    transforms = json::parse(vispack::read_file(dir / "truth/transforms.json"));
  }
};
Streamed& streamed() {
  static Streamed s;
  return s;
}

}  // namespace

TEST(PhantomStreamed, FilesAndSizesAsNlmShipsThem) {
  Streamed& s = streamed();
  const int W = 384, H = 228, C = 282;
  for (int k = 0; k < kSlices; ++k) {
    EXPECT_EQ(fs::file_size(numbered(s.dir / "rgb", "rgb", k, ".raw")), std::uintmax_t(W) * H * 3)
        << k;
    const cv::Mat ct = vispack::pipeline::read_slice(numbered(s.dir / "ct", "ct", k, ".png"));
    EXPECT_EQ(ct.cols, C);
    EXPECT_EQ(ct.rows, C);
    EXPECT_EQ(ct.depth(), CV_16U);
    const cv::Mat seg = vispack::pipeline::read_slice(numbered(s.dir / "seg", "seg", k, ".png"));
    EXPECT_EQ(seg.cols, W);
    EXPECT_EQ(seg.channels(), 3);
  }
  // No truth volume; the truth of every 5th slice, and the list in transforms.json.
  for (const char* v : {"rgb", "ct", "mask", "labels", "seg_labels"})
    EXPECT_FALSE(fs::exists(s.dir / (std::string("truth/") + v + ".nrrd"))) << v;
  const std::vector<int> sample{0, 5, 10, 15};
  EXPECT_EQ(s.summary.truth_sample, sample);
  EXPECT_EQ(s.transforms["truth_sample"].get<std::vector<int>>(), sample);
  std::size_t files = 0;
  for (const auto& e : fs::directory_iterator(s.dir / "truth/sample")) {
    (void)e;
    ++files;
  }
  EXPECT_EQ(files, 2 * sample.size());
  // The estimate the free-space check counted covers what was written.
  std::uintmax_t written = 0;
  for (const auto& e : fs::recursive_directory_iterator(s.dir.path()))
    if (e.is_regular_file()) written += e.file_size();
  EXPECT_GE(s.summary.estimated_bytes, written);
  EXPECT_LE(s.summary.estimated_bytes, 2 * written);
}

TEST(PhantomStreamed, BlockJumpsBlackSlicesAndBrightnessSteps) {
  Streamed& s = streamed();
  const json& slices = s.transforms["slices"];
  std::vector<int> jumps, blacks;
  for (int k = 0; k < kSlices; ++k) {
    if (slices[k]["jump"]) jumps.push_back(k);
    if (slices[k]["black"]) blacks.push_back(k);
  }
  EXPECT_EQ(jumps, (std::vector<int>{4, 8, 12}));
  EXPECT_EQ(jumps, s.summary.jump_slices);
  ASSERT_EQ(blacks.size(), 2u);
  EXPECT_EQ(blacks, s.summary.black_slices);
  for (int k = 0; k < kSlices; ++k) {
    const std::string raw = vispack::read_file(numbered(s.dir / "rgb", "rgb", k, ".raw"));
    const bool all_zero = std::all_of(raw.begin(), raw.end(), [](char c) { return c == 0; });
    EXPECT_EQ(all_zero, std::find(blacks.begin(), blacks.end(), k) != blacks.end()) << k;
  }
  // Each block's brightness factor (1 ± 8 %) times the per-slice gain (1 ± 5 %); the blocks
  // differ.
  const auto gains = s.transforms["block_gains"].get<std::vector<double>>();
  ASSERT_EQ(gains.size(), 4u);
  EXPECT_EQ(s.transforms["block_starts"].get<std::vector<int>>(), (std::vector<int>{0, 4, 8, 12}));
  for (double g : gains) {
    EXPECT_GE(g, 0.92);
    EXPECT_LE(g, 1.08);
  }
  EXPECT_GT(
      *std::max_element(gains.begin(), gains.end()) - *std::min_element(gains.begin(), gains.end()),
      0.01);
  for (int k = 0; k < kSlices; ++k) {
    const double per_slice = double(slices[k]["gain"]) / gains[std::size_t(k / 4)];
    EXPECT_GE(per_slice, 0.95 - 1e-9) << k;
    EXPECT_LE(per_slice, 1.05 + 1e-9) << k;
  }
}

TEST(PhantomStreamed, SampleEqualsTheWholeStackTruthAndTheSlicesAreTheSame) {
  Streamed& s = streamed();
  TempDir whole_dir("vispack-streamed-whole");
  vph::make_phantom(whole_dir.path(), male_options(0));
  const auto mask = vispack::read_nrrd(whole_dir / "truth/mask.nrrd");
  const auto labels = vispack::read_nrrd(whole_dir / "truth/labels.nrrd");
  const std::size_t plane = std::size_t(mask.dims[0]) * mask.dims[1];
  for (int k : s.summary.truth_sample) {
    const cv::Mat m =
        vispack::pipeline::read_slice(numbered(s.dir / "truth/sample", "mask", k, ".png"));
    const cv::Mat l =
        vispack::pipeline::read_slice(numbered(s.dir / "truth/sample", "labels", k, ".png"));
    ASSERT_EQ(m.total(), plane);
    ASSERT_EQ(l.depth(), CV_16U);
    std::size_t differ = 0, body = 0;
    for (std::size_t i = 0; i < plane; ++i) {
      const bool b = mask.as<std::uint8_t>()[plane * k + i] != 0;
      body += b;
      differ += (m.data[i] != 0) != b;
      differ += reinterpret_cast<const std::uint16_t*>(l.data)[i] !=
                labels.as<std::uint16_t>()[plane * k + i];
    }
    EXPECT_EQ(differ, 0u) << k;
    if (k > 0 && k < kSlices - 1) {
      EXPECT_GT(body, plane / 50) << k;
    }
  }
  // The observed slices and the transforms do not depend on how the truth is kept.
  for (int k = 0; k < kSlices; ++k) {
    EXPECT_EQ(vispack::read_file(numbered(s.dir / "rgb", "rgb", k, ".raw")),
              vispack::read_file(numbered(whole_dir / "rgb", "rgb", k, ".raw")))
        << k;
  }
}

TEST(PhantomStreamed, ScoresMasksAndLabelsOnTheSample) {
  Streamed& s = streamed();
  // A work folder holding the truth itself: no drift, IoU 1, every label equal.
  TempDir work("vispack-streamed-work");
  fs::create_directories(work / "register");
  fs::create_directories(work / "mask");
  fs::create_directories(work / "labels");
  fs::copy_file(s.dir / "truth/transforms.json", work / "register/transforms.json");
  for (int k : s.summary.truth_sample) {
    fs::copy_file(numbered(s.dir / "truth/sample", "mask", k, ".png"),
                  numbered(work / "mask", "mask", k, ".png"));
    fs::copy_file(numbered(s.dir / "truth/sample", "labels", k, ".png"),
                  numbered(work / "labels", "labels", k, ".png"));
  }
  const auto perfect = vph::score_work(s.dir / "truth", work.path());
  EXPECT_EQ(perfect.truth_sample, s.summary.truth_sample);
  ASSERT_TRUE(perfect.has_mask);
  ASSERT_TRUE(perfect.has_labels);
  EXPECT_DOUBLE_EQ(perfect.mask.stack_iou, 1.0);
  EXPECT_DOUBLE_EQ(perfect.labels.overall, 1.0);
  EXPECT_DOUBLE_EQ(perfect.drift.rms_px, 0.0);
  EXPECT_EQ(perfect.mask.iou.size(), s.summary.truth_sample.size());
  // Half of slice 10's mask cleared: that slice's IoU drops, and the worst slice is named by its
  // stack index.
  const std::string m10 = numbered(work / "mask", "mask", 10, ".png");
  cv::Mat m = vispack::pipeline::read_slice(m10);
  m.colRange(0, m.cols / 2).setTo(0);
  vispack::pipeline::write_image(m10, m);
  const auto broken = vph::score_work(s.dir / "truth", work.path());
  EXPECT_LT(broken.mask.iou[2], 0.8);
  EXPECT_DOUBLE_EQ(broken.mask.iou[1], 1.0);
  EXPECT_EQ(broken.mask.min_body_slice, 10);
}

TEST(PhantomStreamed, NotEnoughFreeSpaceFailsBeforeWriting) {
  TempDir dir("vispack-streamed-full");
  auto o = male_options(kEvery);
  o.keep_free_bytes = std::numeric_limits<std::uint64_t>::max() / 2;
  const std::string out = dir / "stack";
  try {
    vph::make_phantom(out, o);
    FAIL() << "no error";
  } catch (const vispack::IoError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find(out + ": needs about "), std::string::npos) << what;
    EXPECT_NE(what.find(" bytes kept free but the file system of " + dir.path() + " has "),
              std::string::npos)
        << what;
  }
  EXPECT_FALSE(fs::exists(out));
  // The command line: one line naming the folder, exit status 3 (an I/O error).
  std::string text;
  EXPECT_EQ(vispack::test::run_command(vispack::test::bin("vispack-phantom") +
                                           " --quiet --preset male-small --slices 16 "
                                           "--truth-every 4 --keep-free-gb 1e8 --out " +
                                           out,
                                       &text),
            3)
      << text;
  EXPECT_NE(text.find(out + ": needs about "), std::string::npos) << text;
  EXPECT_FALSE(fs::exists(out));
}

TEST(PhantomStreamed, BlocksAndBlackSlicesThatDoNotFitAreUsageErrors) {
  TempDir dir;
  const std::string cmd = vispack::test::bin("vispack-phantom") +
                          " --quiet --preset tiny --slices 16 --out " + (dir / "p");
  std::string out;
  EXPECT_EQ(vispack::test::run_command(cmd + " --blocks 5", &out), 2) << out;
  EXPECT_NE(out.find("--blocks 5: must be 2..64 and at most slices / 4 (16 slices)"),
            std::string::npos)
      << out;
  EXPECT_EQ(vispack::test::run_command(cmd + " --black-slices 5", &out), 2) << out;
  EXPECT_NE(out.find("--black-slices 5: must be 0..slices / 4"), std::string::npos) << out;
  EXPECT_EQ(vispack::test::run_command(cmd + " --blocks 4 --black-slices 4 --truth-every 4", &out),
            0)
      << out;
}

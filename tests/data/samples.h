// Helpers for the tests on the real sample data (docs/SAMPLES.md): where the converted samples
// are, skipping when they are absent, and the hand-set facts about them that tests check.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include "vispack/pipeline/core/palette.h"

namespace vispack::test {

// Folder of a converted sample: $VISPACK_SAMPLES_DIR/<name> when that variable is set, else
// <source>/data/samples/<name>.
std::string sample_dir(const std::string& name);

// True when the sample was converted completely (its .stamp exists; the script writes it last).
bool sample_present(const std::string& name);

// The message a test prints when it skips for want of the sample.
std::string missing_sample_message(const std::string& name);

// Skips the current test (GTEST_SKIP) when the sample `name` has not been fetched.
#define VISPACK_REQUIRE_SAMPLE(name)                                 \
  do {                                                               \
    if (!::vispack::test::sample_present(name))                      \
      GTEST_SKIP() << ::vispack::test::missing_sample_message(name); \
  } while (0)

// Writes <out_dir>/config.json: the sample's config.json with every input path made absolute and
// work_dir / output / vdb_output moved under out_dir; `edit` may change the JSON further (e.g.
// point seg.dir elsewhere). Returns the path written.
std::string write_sample_config(const std::string& name, const std::string& out_dir,
                                const std::function<void(nlohmann::json&)>& edit = nullptr);

// One palette.json entry.
struct PaletteEntry {
  int id = 0;
  std::string name;
  std::array<int, 3> colour{0, 0, 0};
};
// Reads {"labels":[{"id","name","colour":[r,g,b]}]}. Throws vispack::Error naming the file.
std::vector<PaletteEntry> read_palette(const std::string& path);

// The head CT in HU, slice by slice (CV_16SC1, 256x256), read through the config's ct source
// (list_slices + read_slice, hu = stored * slope + intercept).
std::vector<cv::Mat> read_head_ct_hu();

// --- Head CT: the head-holder arc (docs/SAMPLES.md) ------------------------------------------
// The arc is a thin shell of plastic (HU about 100..600) on a circle of this centre and radius in
// every slice (fitted to slices 0..105, residual <= 3.5 px), in the rows above kArcMaxRow.
inline constexpr double kArcCentreX = 130.4, kArcCentreY = 109.0, kArcRadius = 119.0;
inline constexpr double kArcHalfWidth = 4.0;  // band half-width in px around the circle
inline constexpr int kArcMaxRow = 120;
// True when pixel (x = column, y = row) lies in the arc band (HU must also be > 0 to be arc).
bool in_head_holder_band(int x, int y);

// --- Visible Woman: hand-set bounds on the 142x167 slice (rows y, columns x, inclusive) ------
struct Box {
  int x0, y0, x1, y1;
};
// Brain tissue: must be inside any body mask.
inline constexpr Box kVwInside{25, 80, 105, 140};
// Gel only (no tissue): must be outside any body mask.
inline constexpr std::array<Box, 5> kVwGel{{
    {0, 0, 141, 14},       // top band, full width
    {0, 20, 8, 50},        // left edge strip
    {128, 20, 141, 60},    // right edge strip
    {0, 152, 15, 166},     // bottom-left corner
    {122, 152, 141, 166},  // bottom-right corner
}};

}  // namespace vispack::test

// vispack_test_support: the helpers every test executable links (tests/support/CMakeLists.txt).
//  - TempDir: the one temporary-folder helper of the test suite.
//  - run_command / run_command_split: run a shell command, capture its output.
//  - bin / source_dir: where the built executables and the source tree are.
//  - max_displacement_px: transform error as the largest displacement over an image's four
//    corners and its centre, so a rotation error shows as much as a shift error.
//  - resident_pages: how many pages of a mapping are in memory (mincore).
#pragma once

#include <cstddef>
#include <string>

namespace vispack::test {

// A new empty folder under $TMPDIR (or /tmp), named <prefix>-XXXXXX, removed with everything in
// it when the object dies unless the environment sets VISPACK_KEEP_TEST_DIRS (then its path is
// printed on stderr so it can be found).
class TempDir {
 public:
  explicit TempDir(const std::string& prefix = "vispack-test");
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::string& path() const { return path_; }
  std::string operator/(const std::string& name) const { return path_ + "/" + name; }

 private:
  std::string path_;
};

// Runs a shell command; returns its exit status (0..255; 128 + signal if killed), and its
// stdout+stderr in *output.
int run_command(const std::string& command, std::string* output = nullptr);

// Runs a shell command with stdout and stderr captured apart.
struct CommandResult {
  int code = -1;
  std::string out, err;
};
CommandResult run_command_split(const std::string& command);

// Absolute path of an executable in build/bin ("vispack-phantom").
std::string bin(const std::string& name);
// The source tree's root.
std::string source_dir();

// A rigid transform in the convention of docs/ARCHITECTURE.md: an output-grid point q appears in
// the observed slice at p = c + R(rotation_deg)(q - c) + (dx, dy), c = ((W-1)/2, (H-1)/2).
struct RigidPx {
  double dx = 0, dy = 0, rotation_deg = 0;
};
// The largest |p_a(q) - p_b(q)| over q in {the four corners (0,0), (W-1,0), (0,H-1), (W-1,H-1),
// the centre} of a W x H grid: the error of `a` against the truth `b`, in pixels.
double max_displacement_px(const RigidPx& a, const RigidPx& b, int width, int height);

// A similarity from CT pixels u to the output grid: q = c + scale R(rotation_deg)(u - c_ct) + d,
// c = the output grid's centre, c_ct = the CT image's centre.
struct SimilarityPx {
  double scale = 1, rotation_deg = 0, dx = 0, dy = 0;
};
// The largest |q_a(u) - q_b(u)| in output pixels over u in {the four corners and the centre of
// the CT image (ct_width x ct_height)}.
double max_displacement_px(const SimilarityPx& a, const SimilarityPx& b, int ct_width,
                           int ct_height, int width, int height);

// How many of the pages that [data, data + size) touches are resident (mincore): untouched
// anonymous pages are not. `data` must be page-aligned (a mapping's start). Throws
// std::runtime_error when mincore fails.
std::size_t resident_pages(const void* data, std::size_t size);

}  // namespace vispack::test

// Fuzz target: the config loader. The input is the text of config.json, loaded from a scratch
// folder that holds small rgb/, ct/ and seg/ slice folders and a palette, so that valid configs
// get past the path checks and reach the deeper validation. Any input must give a Config or a
// ConfigError/IoError — never a crash or a hang.
#include <opencv2/core.hpp>

#include <cstring>

#include "fuzz_target.h"
#include "scratch.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace {

// Creates the slice folders once per process.
const std::string& layout_dir() {
  static const std::string dir = [] {
    std::string root = vispack_fuzz_scratch_dir() + "/project";
    for (const char* sub : {"rgb", "ct", "seg"})
      vispack::make_directories(root + "/" + sub);
    cv::Mat rgb(4, 6, CV_8UC3, cv::Scalar(20, 40, 200)), ct(3, 3, CV_16UC1, cv::Scalar(1024));
    for (int k = 0; k < 2; ++k) {
      std::string n = "000" + std::to_string(k);
      vispack::pipeline::write_image(root + "/rgb/rgb_" + n + ".png", rgb);
      vispack::pipeline::write_image(root + "/ct/ct_" + n + ".png", ct);
      vispack::pipeline::write_image(root + "/seg/seg_" + n + ".png", rgb);
    }
    vispack::write_file_atomic(root + "/palette.json",
                               R"({"labels":[{"id":1,"name":"skin","colour":[20,40,200]}]})");
    return root;
  }();
  return dir;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  std::string path = layout_dir() + "/config.json";
  vispack_fuzz_write(path, data, size);
  try {
    vispack::pipeline::Config config = vispack::pipeline::load_config(path);
    (void)vispack::pipeline::config_section_hash(config, {"register", "mask"});
  } catch (const vispack::Error&) {
  }
  return 0;
}

void vispack_fuzz_write_seeds(const std::string& dir) {
  const char* full = R"({
  "name": "fuzz", "work_dir": "work", "output": "out/v.vpk", "vdb_output": "out/v.vdb",
  "spacing_mm": [0.33, 0.33, 1.0],
  "rgb": { "dir": "rgb", "pattern": "rgb_{n}.png" },
  "ct": { "dir": "ct", "pattern": "ct_{n}.png", "pixel_spacing_mm": [0.9, 0.9], "slope": 1.0, "intercept": -1024.0 },
  "seg": { "dir": "seg", "pattern": "seg_{n}.png", "palette": "palette.json", "mode": "colour", "tolerance": 24, "strict": false },
  "register": { "enabled": true, "method": "phase+ecc", "ecc_scale": 0.5, "jump_px": 6.0,
                "output_frame": { "rotation_deg": 0, "dx_px": 0, "dy_px": 0 } },
  "mask": { "hu_threshold": -400, "opening_px": 1, "refine_gel": true },
  "pack": { "brick_edge": 64, "zstd_level": 3, "downsample": 1 },
  "vdb": { "enabled": true }
})";
  const char* minimal = R"({"rgb": {"dir": "rgb", "pattern": "rgb_{n}.png"}})";
  const char* raw = R"({"rgb": {"dir": "rgb", "pattern": "rgb_{n}.png",
    "raw": {"width": 6, "height": 4, "channels": 3, "layout": "planar", "bits": 8, "endian": "little", "header_bytes": 0}}})";
  const char* wrong_type =
      R"({"rgb": {"dir": 5, "pattern": "rgb_{n}.png"}, "pack": {"brick_edge": "big"}})";
  const char* unknown =
      R"({"rgb": {"dir": "rgb", "pattern": "rgb_{n}.png"}, "colour_magic": true})";
  // Fuzzing finding (docs/RELIABILITY.md): a number too large for a double made json::parse
  // throw out_of_range, which load_config let escape instead of a ConfigError.
  const char* overflow = "777777E79999";
  const char* overflow_in_key =
      R"({"rgb": {"dir": "rgb", "pattern": "rgb_{n}.png"}, "spacing_mm": [1E99999, 1, 1]})";
  int i = 0;
  for (const char* text : {full, minimal, raw, wrong_type, unknown, overflow, overflow_in_key}) {
    vispack_fuzz_write(dir + "/config-" + std::to_string(i++) + ".json", text, std::strlen(text));
  }
}

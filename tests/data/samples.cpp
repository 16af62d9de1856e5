#include "samples.h"

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>

#include "vispack/common/error.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/palette.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vispack::test {

std::string sample_dir(const std::string& name) {
  const char* env = std::getenv("VISPACK_SAMPLES_DIR");
  std::string root =
      (env && *env) ? std::string(env) : std::string(VISPACK_SOURCE_DIR) + "/data/samples";
  return root + "/" + name;
}

bool sample_present(const std::string& name) {
  return std::filesystem::exists(sample_dir(name) + "/.stamp");
}

std::string missing_sample_message(const std::string& name) {
  return cat("real sample '", name, "' not found at ", sample_dir(name),
             "; run scripts/fetch-sample-data.sh to fetch and convert it");
}

std::string write_sample_config(const std::string& name, const std::string& out_dir,
                                const std::function<void(nlohmann::json&)>& edit) {
  const std::string dir = sample_dir(name);
  std::ifstream in(dir + "/config.json");
  if (!in) throw IoError(cat(dir, "/config.json: cannot open"));
  nlohmann::json j = nlohmann::json::parse(in, nullptr, true, true);
  for (const char* section : {"rgb", "ct", "seg"}) {
    if (!j.contains(section)) continue;
    auto& s = j[section];
    if (s.contains("dir")) s["dir"] = dir + "/" + s["dir"].get<std::string>();
    if (s.contains("palette")) s["palette"] = dir + "/" + s["palette"].get<std::string>();
  }
  j["work_dir"] = out_dir + "/work";
  j["output"] = out_dir + "/volume.vpk";
  j["vdb_output"] = out_dir + "/volume.vdb";
  if (edit) edit(j);
  const std::string path = out_dir + "/config.json";
  std::ofstream out(path);
  out << j.dump(2) << "\n";
  if (!out) throw IoError(cat(path, ": cannot write"));
  return path;
}

std::vector<PaletteEntry> read_palette(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw IoError(cat(path, ": cannot open"));
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(in);
  } catch (const std::exception& e) {
    throw FormatError(cat(path, ": ", e.what()));
  }
  std::vector<PaletteEntry> out;
  for (const auto& l : j.at("labels")) {
    PaletteEntry e;
    e.id = l.at("id").get<int>();
    e.name = l.at("name").get<std::string>();
    for (int c = 0; c < 3; ++c)
      e.colour[c] = l.at("colour").at(c).get<int>();
    out.push_back(e);
  }
  return out;
}

std::vector<cv::Mat> read_head_ct_hu() {
  auto config = pipeline::load_config(sample_dir("head-ct") + "/config.json");
  if (!config.ct) throw Error("head-ct config has no ct section");
  std::vector<cv::Mat> out;
  for (const auto& file : pipeline::list_slices(*config.ct)) {
    cv::Mat stored = pipeline::read_slice(file.path, config.ct->raw);
    if (stored.type() != CV_16UC1) throw Error(cat(file.path, ": not 16-bit grey"));
    cv::Mat hu;
    stored.convertTo(hu, CV_16S, config.ct->slope, config.ct->intercept);
    out.push_back(hu);
  }
  return out;
}

bool in_head_holder_band(int x, int y) {
  if (y > kArcMaxRow) return false;
  double r = std::hypot(x - kArcCentreX, y - kArcCentreY);
  return std::abs(r - kArcRadius) <= kArcHalfWidth;
}

}  // namespace vispack::test

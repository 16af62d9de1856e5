// load_config: every key checked, defaults, relative paths; configs/schema.json agrees with the
// loader key for key.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <set>
#include <sstream>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/core/config.h"

using namespace vispack;
using namespace vispack::pipeline;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

void touch(const std::string& path) {
  fs::create_directories(fs::path(path).parent_path());
  std::ofstream(path) << "x";
}

// A folder with rgb/, ct/, seg/ slices (names only: the loader does not read pixels),
// palette.json and id_map.json.
void make_inputs(const test::TempDir& dir) {
  for (int i = 0; i < 3; ++i) {
    char name[64];
    std::snprintf(name, sizeof name, "%04d", i);
    touch(dir / (std::string("data/rgb/rgb_") + name + ".png"));
    touch(dir / (std::string("data/ct/ct_") + name + ".png"));
    touch(dir / (std::string("data/seg/seg_") + name + ".png"));
    touch(dir / (std::string("data/raw/c") + name + ".raw"));
  }
  write_file_atomic(dir / "data/palette.json",
                    R"({"labels":[{"id":1,"name":"a","colour":[1,2,3]}]})");
  write_file_atomic(dir / "data/id_map.json", R"({"1": 2})");
  write_file_atomic(dir / "data/overrides.json", R"({"slices": []})");
}

// Every key the loader accepts, with a valid value (seg in mode "id" so that id_map is allowed).
json full_config() {
  return json::parse(R"({
    "name": "full", "work_dir": "w", "output": "o/v.vpk", "vdb_output": "o/v.vdb",
    "spacing_mm": [0.33, 0.33, 1.0],
    "rgb": { "dir": "data/raw", "pattern": "c{n}.raw",
             "raw": { "width": 16, "height": 8, "channels": 3, "layout": "planar", "bits": 8,
                      "endian": "little", "header_bytes": 0, "header": "none" } },
    "ct": { "dir": "data/ct", "pattern": "ct_{n}.png", "pixel_spacing_mm": [0.9, 0.9],
            "slope": 1.0, "intercept": -1024.0, "slice_spacing_mm": 3.0, "z_offset_mm": -1.5,
            "raw": { "width": 4, "height": 4, "channels": 1, "layout": "interleaved", "bits": 16,
                     "endian": "big", "header_bytes": 10, "header": "none" } },
    "seg": { "dir": "data/seg", "pattern": "seg_{n}.png", "palette": "data/palette.json",
             "mode": "id", "tolerance": 24, "strict": false, "id_map": "data/id_map.json",
             "slice_spacing_mm": 0.5, "z_offset_mm": 0.25,
             "raw": { "width": 16, "height": 8, "channels": 1, "layout": "interleaved", "bits": 16,
                      "endian": "little", "header_bytes": 0, "header": "none" } },
    "register": { "enabled": true, "method": "phase+ecc", "ecc_scale": 0.5, "ecc_iterations": 50,
                  "jump_px": 6.0, "anchor": "ct", "ct_anchor_between": "interpolated",
                  "overrides": "data/overrides.json",
                  "output_frame": { "rotation_deg": 1.5, "dx_px": -2, "dy_px": 3 } },
    "mask": { "hu_threshold": -400, "opening_px": 1, "refine_gel": true, "gel_colour": [30, 60, 200],
              "gel_distance": 40, "min_part_mm2": 5 },
    "pack": { "brick_edge": 64, "zstd_level": 3, "downsample": 1, "threads": 0,
              "keep_outside_body": "ct", "crop_margin_px": 8 },
    "work": { "write_registered": true, "write_ct": false, "overlay_max_px": 512 },
    "vdb": { "enabled": true, "level": 1, "layout": "file", "max_memory_mb": 4096 }
  })");
}

std::string write_config(const test::TempDir& dir, const json& config,
                         const std::string& name = "c.json") {
  std::string path = dir / name;
  write_file_atomic(path, config.dump(2));
  return path;
}

// Runs load_config and returns the ConfigError message ("" when it loads).
std::string config_error(const std::string& path) {
  try {
    load_config(path);
  } catch (const ConfigError& e) {
    return e.what();
  }
  return "";
}

// Follows "$ref": "#/$defs/x" inside the schema.
const json& deref(const json& schema, const json& node) {
  if (node.is_object() && node.contains("$ref")) {
    std::string ref = node["$ref"];
    const std::string prefix = "#/$defs/";
    EXPECT_EQ(ref.rfind(prefix, 0), 0u) << ref;
    return schema["$defs"][ref.substr(prefix.size())];
  }
  return node;
}

// Key paths ("ct.raw.width") of every property in the schema.
void schema_keys(const json& schema, const json& node, const std::string& prefix,
                 std::set<std::string>& out) {
  const json& n = deref(schema, node);
  if (!n.is_object() || !n.contains("properties")) return;
  for (auto& [key, child] : n["properties"].items()) {
    std::string path = prefix.empty() ? key : prefix + "." + key;
    out.insert(path);
    schema_keys(schema, child, path, out);
  }
}

void config_keys(const json& node, const std::string& prefix, std::set<std::string>& out) {
  if (!node.is_object()) return;
  for (auto& [key, child] : node.items()) {
    std::string path = prefix.empty() ? key : prefix + "." + key;
    out.insert(path);
    config_keys(child, path, out);
  }
}

// A minimal JSON-Schema check of the subset schema.json uses (type, enum, const-free ranges,
// array sizes, additionalProperties false, required). Returns "" or the first problem.
std::string schema_check(const json& schema, const json& node_in, const json& value,
                         const std::string& where) {
  const json& node = deref(schema, node_in);
  if (node.contains("type")) {
    std::vector<std::string> types;
    if (node["type"].is_array())
      for (auto& t : node["type"])
        types.push_back(t);
    else
      types.push_back(node["type"]);
    bool ok = false;
    for (auto& t : types) {
      if ((t == "object" && value.is_object()) || (t == "array" && value.is_array()) ||
          (t == "string" && value.is_string()) || (t == "boolean" && value.is_boolean()) ||
          (t == "number" && value.is_number()) || (t == "null" && value.is_null()) ||
          (t == "integer" && (value.is_number_integer() || value.is_number_unsigned())))
        ok = true;
    }
    if (!ok) return where + ": wrong type";
  }
  if (node.contains("enum")) {
    bool ok = false;
    for (auto& e : node["enum"])
      ok = ok || e == value;
    if (!ok) return where + ": not in enum";
  }
  if (value.is_number()) {
    double x = value;
    if (node.contains("minimum") && x < double(node["minimum"])) return where + ": below minimum";
    if (node.contains("maximum") && x > double(node["maximum"])) return where + ": above maximum";
    if (node.contains("exclusiveMinimum") && x <= double(node["exclusiveMinimum"]))
      return where + ": below exclusiveMinimum";
  }
  if (value.is_array()) {
    if (node.contains("minItems") && value.size() < node["minItems"])
      return where + ": too few items";
    if (node.contains("maxItems") && value.size() > node["maxItems"])
      return where + ": too many items";
    if (node.contains("items"))
      for (std::size_t i = 0; i < value.size(); ++i) {
        std::string r =
            schema_check(schema, node["items"], value[i], where + "[" + std::to_string(i) + "]");
        if (!r.empty()) return r;
      }
  }
  if (value.is_object()) {
    if (node.contains("required"))
      for (auto& key : node["required"])
        if (!value.contains(key.get<std::string>()))
          return where + ": missing " + key.get<std::string>();
    for (auto& [key, child] : value.items()) {
      if (key[0] == '_') continue;
      if (node.contains("properties") && node["properties"].contains(key)) {
        std::string r = schema_check(schema, node["properties"][key], child, where + "." + key);
        if (!r.empty()) return r;
      } else if (node.value("additionalProperties", true) == false) {
        return where + "." + key + ": not allowed";
      }
    }
  }
  return "";
}

json load_schema() {
  return json::parse(read_file(std::string(VISPACK_SOURCE_DIR) + "/configs/schema.json"));
}

}  // namespace

TEST(Config, FullConfigLoadsWithResolvedPaths) {
  test::TempDir dir;
  make_inputs(dir);
  Config c = load_config(write_config(dir, full_config()));
  EXPECT_EQ(c.name, "full");
  EXPECT_EQ(c.work_dir, dir / "w");
  EXPECT_EQ(c.output, dir / "o/v.vpk");
  EXPECT_EQ(c.vdb_output, dir / "o/v.vdb");
  EXPECT_EQ(c.rgb.dir, dir / "data/raw");
  ASSERT_TRUE(c.rgb.raw.has_value());
  EXPECT_EQ(c.rgb.raw->width, 16);
  EXPECT_TRUE(c.rgb.raw->planar);
  ASSERT_TRUE(c.ct.has_value());
  EXPECT_TRUE(c.ct->raw->big_endian);
  EXPECT_EQ(c.ct->raw->bits, 16);
  EXPECT_EQ(c.ct->raw->header_bytes, 10u);
  EXPECT_DOUBLE_EQ(c.ct->pixel_spacing_mm[0], 0.9);
  ASSERT_TRUE(c.seg.has_value());
  EXPECT_EQ(c.seg->mode, "id");
  EXPECT_EQ(c.seg->id_map, dir / "data/id_map.json");
  EXPECT_EQ(c.seg->raw->channels, 1);
  EXPECT_DOUBLE_EQ(c.registration.output_frame.rotation_deg, 1.5);
  EXPECT_DOUBLE_EQ(c.registration.output_frame.dy_px, 3.0);
  EXPECT_EQ(c.registration.anchor, "ct");
  EXPECT_EQ(c.registration.overrides, dir / "data/overrides.json");
  ASSERT_TRUE(c.mask.gel_colour.has_value());
  EXPECT_EQ((*c.mask.gel_colour)[2], 200);
  EXPECT_EQ(c.pack.brick_edge, 64);
  EXPECT_FALSE(c.pack.keep_colour_outside_body);
  EXPECT_TRUE(c.pack.keep_ct_outside_body);
  ASSERT_TRUE(c.pack.crop_margin_px.has_value());
  EXPECT_EQ(*c.pack.crop_margin_px, 8);
  EXPECT_TRUE(c.work.write_registered);
  EXPECT_FALSE(c.work.write_ct);
  EXPECT_EQ(c.work.overlay_max_px, 512);
}

TEST(Config, DefaultsForAMinimalConfig) {
  test::TempDir dir;
  make_inputs(dir);
  json j = {{"spacing_mm", {1, 1, 2}}, {"rgb", {{"dir", "data/rgb"}}}};
  Config c = load_config(write_config(dir, j, "minimal.json"));
  EXPECT_EQ(c.name, "minimal");
  EXPECT_EQ(c.work_dir, dir / "work");
  EXPECT_EQ(c.output, dir / "out/minimal.vpk");
  EXPECT_EQ(c.vdb_output, dir / "out/minimal.vdb");
  EXPECT_EQ(c.rgb.pattern, "rgb_{n}.png");
  EXPECT_FALSE(c.ct.has_value());
  EXPECT_FALSE(c.seg.has_value());
  EXPECT_EQ(c.registration.method, "phase+ecc");
  EXPECT_DOUBLE_EQ(c.mask.hu_threshold, -400.0);
  EXPECT_DOUBLE_EQ(c.mask.min_part_mm2, 5.0);
  EXPECT_EQ(c.pack.zstd_level, 3);
  // By default (docs/ARCHITECTURE.md, 'The packed file') colour and CT outside the body are cleared
  // and nothing is cropped.
  EXPECT_FALSE(c.pack.keep_colour_outside_body);
  EXPECT_FALSE(c.pack.keep_ct_outside_body);
  EXPECT_FALSE(c.pack.crop_margin_px.has_value());
  // No full-size registered (docs/ARCHITECTURE.md, 'Work folder layout') colour or CT copies;
  // overlays at most 1024 px.
  EXPECT_FALSE(c.work.write_registered);
  EXPECT_FALSE(c.work.write_ct);
  EXPECT_EQ(c.work.overlay_max_px, 1024);
  EXPECT_TRUE(c.vdb.enabled);
  j["vdb"] = {{"enabled", false}};
  EXPECT_EQ(load_config(write_config(dir, j, "minimal.json")).vdb_output, "");
}

TEST(Config, ErrorsNameTheKey) {
  test::TempDir dir;
  make_inputs(dir);
  struct Case {
    std::function<void(json&)> edit;
    std::string expected;  // a substring of the error
  };
  std::vector<Case> cases = {
      {[](json& j) { j["colour"] = 1; }, "colour: unknown key"},
      {[](json& j) { j["ct"]["pixel_spacing"] = 1; }, "ct.pixel_spacing: unknown key"},
      {[](json& j) { j["ct"]["pixel_spacing_mm"] = "0.9"; },
       "ct.pixel_spacing_mm: must be an array"},
      {[](json& j) {
         j["ct"]["pixel_spacing_mm"] = {0.9, -1};
       },
       "ct.pixel_spacing_mm[1]"},
      {[](json& j) { j["ct"].erase("pixel_spacing_mm"); }, "ct.pixel_spacing_mm: missing"},
      {[](json& j) {
         j["spacing_mm"] = {1, 1};
       },
       "spacing_mm: must be an array of 3"},
      {[](json& j) { j.erase("rgb"); }, "rgb: missing"},
      {[](json& j) { j["rgb"]["dir"] = "nowhere"; }, "rgb.dir: folder"},
      {[](json& j) { j["rgb"]["pattern"] = "x_{n}.tif"; }, "rgb.pattern"},
      {[](json& j) { j["rgb"]["pattern"] = "rgb.png"; }, "rgb.pattern: \"rgb.png\" has no {n}"},
      {[](json& j) { j["rgb"]["raw"]["layout"] = "tiled"; },
       "rgb.raw.layout: \"tiled\" is not one of"},
      {[](json& j) { j["rgb"]["raw"]["bits"] = 12; }, "rgb.raw.bits: must be 8 or 16"},
      {[](json& j) { j["rgb"]["raw"].erase("width"); }, "rgb.raw.width: missing"},
      {[](json& j) { j["ct"]["raw"]["header"] = "dicom"; },
       "ct.raw.header: \"dicom\" is not one of"},
      {[](json& j) { j["ct"]["raw"]["header"] = "genesis"; },
       "ct.raw.header_bytes: not used with header \"genesis\" (each file's own header gives the "
       "pixel offset); remove it"},
      {[](json& j) { j["rgb"]["raw"]["header"] = "genesis"; },
       "rgb.raw.channels: must be 1 with header \"genesis\""},
      {[](json& j) { j["seg"]["palette"] = "none.json"; }, "seg.palette: file"},
      {[](json& j) { j["seg"]["mode"] = "colour"; }, "seg.id_map: only allowed in mode \"id\""},
      {[](json& j) { j["seg"]["tolerance"] = 500; }, "seg.tolerance: 500 is out of range"},
      {[](json& j) { j["seg"]["strict"] = 1; }, "seg.strict: must be true or false"},
      {[](json& j) { j["register"]["method"] = "sift"; }, "register.method"},
      {[](json& j) { j["register"]["ecc_scale"] = 0; }, "register.ecc_scale: 0 is out of range (0"},
      {[](json& j) { j["register"]["output_frame"]["dx_px"] = "big"; },
       "register.output_frame.dx_px: must be a number"},
      {[](json& j) { j["register"]["ct_initial"] = json::object(); },
       "register.ct_initial: unknown key"},
      {[](json& j) { j["register"]["anchor"] = "gps"; }, "register.anchor: \"gps\" is not one of"},
      {[](json& j) { j.erase("ct"); }, "register.anchor: \"ct\" needs a \"ct\" section"},
      {[](json& j) { j["register"]["overrides"] = "none.json"; }, "register.overrides: file"},
      {[](json& j) { j["mask"]["opening_px"] = 1.5; }, "mask.opening_px: must be an integer"},
      {[](json& j) { j["mask"]["min_part_mm2"] = -1; }, "mask.min_part_mm2: -1 is out of range"},
      {[](json& j) { j["mask"]["min_part_mm2"] = "big"; }, "mask.min_part_mm2: must be a number"},
      {[](json& j) {
         j["mask"]["gel_colour"] = {1, 2, 300};
       },
       "mask.gel_colour[2]"},
      {[](json& j) { j["pack"]["brick_edge"] = 48; }, "pack.brick_edge: 48 is not a power of two"},
      {[](json& j) { j["pack"]["zstd_level"] = 23; }, "pack.zstd_level: 23 is out of range"},
      {[](json& j) { j["pack"]["keep_outside_body"] = true; },
       "pack.keep_outside_body: must be a string, got a boolean"},
      {[](json& j) { j["pack"]["keep_outside_body"] = "gel"; },
       "pack.keep_outside_body: \"gel\" is not one of \"none\", \"colour\", \"ct\", \"all\""},
      {[](json& j) { j["pack"]["crop_margin_px"] = -1; },
       "pack.crop_margin_px: -1 is out of range"},
      {[](json& j) { j["pack"]["crop_margin_px"] = 2.5; },
       "pack.crop_margin_px: must be an integer, got a number"},
      {[](json& j) { j["work"]["write_ct"] = "yes"; }, "work.write_ct: must be true or false"},
      {[](json& j) { j["work"]["overlay_max_px"] = 8; },
       "work.overlay_max_px: 8 is too small (0 = full size, else >= 16)"},
      {[](json& j) { j["work"]["keep"] = true; }, "work.keep: unknown key"},
      {[](json& j) { j["vdb"]["enable"] = true; }, "vdb.enable: unknown key"},
      {[](json& j) { j["vdb_output"] = j["output"]; }, "vdb_output: must differ from output"},
  };
  for (const auto& c : cases) {
    json j = full_config();
    c.edit(j);
    std::string error = config_error(write_config(dir, j));
    EXPECT_NE(error.find(c.expected), std::string::npos)
        << "expected '" << c.expected << "' in '" << error << "' for " << j.dump();
    EXPECT_NE(error.find(dir / "c.json"), std::string::npos) << error;
  }
}

// raw.header "genesis" (the VH male's CT .fre files, slice_io.h): no header_bytes, samples
// big-endian unless endian says otherwise; written back by the config writer.
TEST(Config, GenesisHeaderDefaultsToBigEndian) {
  test::TempDir dir;
  make_inputs(dir);
  json j = full_config();
  j["ct"]["raw"].erase("header_bytes");
  j["ct"]["raw"].erase("endian");
  j["ct"]["raw"]["header"] = "genesis";
  const Config c = load_config(write_config(dir, j));
  ASSERT_TRUE(c.ct && c.ct->raw);
  EXPECT_TRUE(c.ct->raw->genesis);
  EXPECT_TRUE(c.ct->raw->big_endian);
  EXPECT_EQ(c.ct->raw->header_bytes, 0u);
  // The CT's pixel spacing goes with it: read_slice checks each file's recorded pixel size.
  ASSERT_TRUE(c.ct->raw->genesis_pixel_mm);
  EXPECT_EQ(*c.ct->raw->genesis_pixel_mm, c.ct->pixel_spacing_mm);
  EXPECT_FALSE(c.rgb.raw->genesis);
  EXPECT_FALSE(c.rgb.raw->genesis_pixel_mm);
  j["ct"]["raw"]["endian"] = "little";
  EXPECT_FALSE(load_config(write_config(dir, j)).ct->raw->big_endian);
}

TEST(Config, CommentsAreAccepted) {
  test::TempDir dir;
  make_inputs(dir);
  write_file_atomic(dir / "commented.json", R"({
    // a line comment
    "_comment": "underscore keys are comments",
    "spacing_mm": [1, 1, 1], /* a block comment */
    "rgb": { "dir": "data/rgb", "_note": "ignored too" }
  })");
  EXPECT_EQ(load_config(dir / "commented.json").spacing_mm[2], 1.0);
  write_file_atomic(dir / "broken.json", R"({ "spacing_mm": [1, 1, 1], )");
  EXPECT_NE(config_error(dir / "broken.json").find("not valid JSON"), std::string::npos);
  EXPECT_THROW(load_config(dir / "absent.json"), IoError);
}

TEST(Config, SectionHashTracksOnlyItsSections) {
  test::TempDir dir;
  make_inputs(dir);
  json j = full_config();
  Config a = load_config(write_config(dir, j));
  j["mask"]["hu_threshold"] = -300;
  j["pack"]["_comment"] = "comments do not change hashes";
  Config b = load_config(write_config(dir, j));
  EXPECT_EQ(config_section_hash(a, {"register", "rgb"}),
            config_section_hash(b, {"register", "rgb"}));
  EXPECT_EQ(config_section_hash(a, {"pack"}), config_section_hash(b, {"pack"}));
  EXPECT_NE(config_section_hash(a, {"mask"}), config_section_hash(b, {"mask"}));
  EXPECT_NE(config_section_hash(a, {"register", "mask"}),
            config_section_hash(b, {"register", "mask"}));
  EXPECT_EQ(config_section_hash(a, {"mask"}).size(), 16u);
  // Single keys: register may depend on mask.gel_distance without depending on hu_threshold.
  EXPECT_EQ(config_section_hash(a, {"mask.gel_distance"}),
            config_section_hash(b, {"mask.gel_distance"}));
  EXPECT_NE(config_section_hash(a, {"mask.hu_threshold"}),
            config_section_hash(b, {"mask.hu_threshold"}));
  EXPECT_NE(config_section_hash(a, {"mask.gel_distance"}),
            config_section_hash(a, {"mask.hu_threshold"}));
}

// The schema and the loader accept the same keys: the full config uses every key of the
// schema and nothing else, validates against the schema, and loads; removing any key of it that
// the schema does not require still loads, and renaming any key makes both reject it.
TEST(Config, SchemaAndLoaderAgreeKeyForKey) {
  test::TempDir dir;
  make_inputs(dir);
  json schema = load_schema();
  std::set<std::string> in_schema, in_config;
  schema_keys(schema, schema, "", in_schema);
  json full = full_config();
  config_keys(full, "", in_config);
  for (const auto& key : in_schema)
    EXPECT_TRUE(in_config.count(key)) << key << " is in the schema only";
  for (const auto& key : in_config)
    EXPECT_TRUE(in_schema.count(key)) << key << " is in the test config only";
  // The loader's own table of keys (used for unknown-key errors) agrees too.
  std::set<std::string> in_loader;
  for (const auto& key : config_key_paths())
    in_loader.insert(key);
  EXPECT_EQ(in_loader, in_config);
  EXPECT_EQ(schema_check(schema, schema, full, "$"), "");
  EXPECT_EQ(config_error(write_config(dir, full)), "");

  for (const std::string& key : in_config) {
    // Rename the key: the loader must name it as unknown, the schema must refuse it.
    json j = full;
    json* parent = &j;
    std::string last = key;
    for (std::size_t dot; (dot = last.find('.')) != std::string::npos; last = last.substr(dot + 1))
      parent = &(*parent)[last.substr(0, dot)];
    (*parent)[last + "_typo"] = (*parent)[last];
    parent->erase(last);
    std::string error = config_error(write_config(dir, j));
    EXPECT_NE(error.find(key + "_typo: unknown key"), std::string::npos) << key << ": " << error;
    EXPECT_NE(schema_check(schema, schema, j, "$"), "") << key;
  }
  // Sample configs shipped in configs/ validate against the schema too.
  for (const char* name : {"phantom-small.json", "vhp-male.template.json",
                           "vhp-female.template.json", "vkh-head.template.json"}) {
    json sample = json::parse(read_file(std::string(VISPACK_SOURCE_DIR) + "/configs/" + name),
                              nullptr, true, true);
    EXPECT_EQ(schema_check(schema, schema, sample, "$"), "") << name;
  }
}

namespace {

// The lines of a ConfigError's message (one per error).
std::vector<std::string> error_lines(const std::string& message) {
  std::vector<std::string> lines;
  std::istringstream in(message);
  for (std::string line; std::getline(in, line);)
    lines.push_back(line);
  return lines;
}

}  // namespace

// Several errors in several sections: all of them in one run, one line each, in file order,
// each naming the file and its key.
TEST(Config, EveryErrorIsReportedInOneRun) {
  test::TempDir dir;
  make_inputs(dir);
  json j = full_config();
  j["spacing_mm"] = {1, 1};       // wrong shape
  j["ct"]["slope"] = 0;           // a check after the type check
  j["seg"]["tolerance"] = 500;    // out of range
  j["mask"]["opening_px"] = 1.5;  // wrong type
  j["pack"]["brick_edge"] = 48;   // not a power of two
  j["vdb"]["enable"] = true;      // unknown key
  j["rgb"]["dir"] = "nowhere";    // missing folder
  const std::string path = write_config(dir, j);
  const std::vector<std::string> lines = error_lines(config_error(path));
  const std::vector<std::string> expected = {
      "vdb.enable: unknown key (did you mean vdb.enabled?)",
      "spacing_mm: must be an array of 3 numbers",
      "rgb.dir: folder",
      "ct.slope: must not be 0",
      "seg.tolerance: 500 is out of range",
      "mask.opening_px: must be an integer",
      "pack.brick_edge: 48 is not a power of two",
  };
  ASSERT_EQ(lines.size(), expected.size()) << config_error(path);
  for (std::size_t i = 0; i < lines.size(); ++i) {
    EXPECT_EQ(lines[i].rfind(path + ": ", 0), 0u) << lines[i];
    EXPECT_NE(lines[i].find(expected[i]), std::string::npos)
        << "line " << i << ": expected '" << expected[i] << "' in '" << lines[i] << "'";
  }
  // Each error alone gives its own line only.
  json one = full_config();
  one["seg"]["tolerance"] = 500;
  EXPECT_EQ(error_lines(config_error(write_config(dir, one))).size(), 1u);
}

// More errors than the limit: the first kMaxConfigErrors lines and one line counting the rest.
TEST(Config, ErrorsAreListedUpToTheLimit) {
  test::TempDir dir;
  make_inputs(dir);
  json j = full_config();
  const std::size_t extra = 5;
  for (std::size_t i = 0; i < kMaxConfigErrors + extra; ++i)
    j["mask"][cat("zz", i, "_no_such_key_at_all")] = 1;
  const std::string path = write_config(dir, j);
  const std::vector<std::string> lines = error_lines(config_error(path));
  ASSERT_EQ(lines.size(), kMaxConfigErrors + 1) << config_error(path);
  for (std::size_t i = 0; i < kMaxConfigErrors; ++i)
    EXPECT_NE(lines[i].find(": unknown key"), std::string::npos) << lines[i];
  EXPECT_EQ(lines.back(), cat(path, ": ", extra, " more errors not shown (the first ",
                              kMaxConfigErrors, " are above)"));
}

// An unknown key names the known key of its object that it most likely misspells; a required
// key it stands for is not reported missing a second time; a key like no known one gets no guess.
TEST(Config, UnknownKeyNamesTheNearestKnownKey) {
  test::TempDir dir;
  make_inputs(dir);
  struct Case {
    std::function<void(json&)> edit;
    std::vector<std::string> expected;  // the whole error, line by line, after "FILE: "
  };
  auto rename = [](json& object, const std::string& from, const std::string& to) {
    object[to] = object[from];
    object.erase(from);
  };
  const std::vector<Case> cases = {
      {[&](json& j) { rename(j["ct"], "slice_spacing_mm", "slice_spacing"); },
       {"ct.slice_spacing: unknown key (did you mean ct.slice_spacing_mm?)"}},
      {[&](json& j) { rename(j["rgb"], "dir", "dri"); },
       {"rgb.dri: unknown key (did you mean rgb.dir?)"}},
      {[&](json& j) { rename(j, "spacing_mm", "Spacing_MM"); },
       {"Spacing_MM: unknown key (did you mean spacing_mm?)"}},
      {[&](json& j) { rename(j["mask"], "gel_colour", "gel_color"); },
       {"mask.gel_color: unknown key (did you mean mask.gel_colour?)"}},
      {[&](json& j) { j["colour_slices"] = "x"; }, {"colour_slices: unknown key"}},
      // Two typos in one object and one elsewhere: three lines.
      {[&](json& j) {
         rename(j["pack"], "zstd_level", "zstd_levle");
         rename(j["pack"], "threads", "thread");
         rename(j["work"], "write_ct", "writ_ct");
       },
       {"pack.thread: unknown key (did you mean pack.threads?)",
        "pack.zstd_levle: unknown key (did you mean pack.zstd_level?)",
        "work.writ_ct: unknown key (did you mean work.write_ct?)"}},
  };
  for (const auto& c : cases) {
    json j = full_config();
    c.edit(j);
    const std::string path = write_config(dir, j);
    std::vector<std::string> expected;
    for (const auto& line : c.expected)
      expected.push_back(path + ": " + line);
    EXPECT_EQ(error_lines(config_error(path)), expected) << j.dump();
  }
  EXPECT_EQ(nearest_key("slice_spacing", {"slice_spacing_mm", "z_offset_mm"}), "slice_spacing_mm");
  EXPECT_EQ(nearest_key("hieght", {"width", "height"}), "height");
  EXPECT_EQ(nearest_key("colour", {"dir", "pattern", "raw"}), "");
  EXPECT_EQ(nearest_key("xt", {"ct"}), "");
}

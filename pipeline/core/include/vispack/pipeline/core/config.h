// The pipeline configuration: one JSON file (docs/ARCHITECTURE.md "The config",
// configs/schema.json).
//
// load_config() checks every key: an unknown key, a wrong type, a value out of range, a missing
// folder or a pattern that matches no file is a ConfigError naming the key (as a JSON path such
// as "ct.pixel_spacing_mm") or the path. Every error in the file is reported at once: the
// ConfigError's message holds one line per error ("FILE: KEY: MESSAGE", in the order found, at
// most kMaxConfigErrors lines and then one line counting the rest); an unknown key names the known
// key of its object nearest in spelling ("did you mean ct.slice_spacing_mm?"). Relative paths are
// resolved against the config file's folder; every path in Config is absolute. Defaults fill
// every key that has a sensible default.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "vispack/pipeline/core/transform_types.h"

namespace vispack::pipeline {

// Layout of header-less raw slices (NLM Visible Human style).
struct RawLayout {
  int width = 0, height = 0;
  int channels = 1;     // 1 (grey) or 3 (RGB)
  bool planar = false;  // true: all R, then all G, then all B ("non-interleaved")
  int bits = 8;         // 8 or 16
  bool big_endian = false;
  std::uint64_t header_bytes = 0;  // bytes skipped at the start of each file
  // raw.header "genesis": each file is a GE Genesis (Signa 5.x) image, the NLM male's CT .fre:
  // the pixel data's offset, width, height and bit depth come from the file's own header (magic
  // "IMGF"), checked against width, height and bits; header_bytes is unused (0). Big-endian
  // samples unless `endian` says otherwise (slice_io.h read_slice).
  bool genesis = false;
  // With `genesis`, the CT's ct.pixel_spacing_mm (set by the config loader, not a raw key): a file
  // whose image header records a pixel size more than 1 % off it is refused (genesis.h).
  std::optional<std::array<double, 2>> genesis_pixel_mm = std::nullopt;
};

// One slice folder: files matched by `pattern` ({n} = the slice number), sorted by number.
struct SliceSource {
  std::string dir;               // absolute
  std::string pattern;           // e.g. "rgb_{n}.png"
  std::optional<RawLayout> raw;  // header-less raw slices when set; else an image file (slice_io.h)
};

struct CtSource : SliceSource {
  std::array<double, 2> pixel_spacing_mm{1.0, 1.0};
  double slope = 1.0;  // hu = stored * slope + intercept
  double intercept = -1024.0;
  // Along z (slice_z.h): CT slice j (stack index, sorted by number) lies at
  // z = z_offset_mm + j · slice_spacing_mm, colour slice k at k · spacing_mm[2] (mm).
  // ct.slice_spacing_mm: load_config fills in spacing_mm[2] when the key is absent; unset in a
  // Config built in code means the same.
  std::optional<double> slice_spacing_mm;
  double z_offset_mm = 0.0;  // ct.z_offset_mm: z of CT slice 0 minus z of colour slice 0
};

struct SegSource : SliceSource {
  std::string palette;          // absolute path of palette.json
  std::string mode = "colour";  // "colour" (colour-coded) or "id" (integer label images)
  double tolerance = 24.0;      // max Euclidean RGB distance for nearest-colour matching
  bool strict = false;          // an out-of-tolerance colour is an error instead of label 0
  std::string id_map;           // mode "id": optional JSON {"<input id>": <output id>}, absolute
  // Along z (slice_z.h). seg.slice_spacing_mm unset (the default): segmentation slices
  // are matched to colour slices by the number in the file name. Set: segmentation slice j (stack
  // index) lies at z = z_offset_mm + j · slice_spacing_mm and each colour slice takes the one
  // nearest in z (none within half a spacing: label 0, listed).
  std::optional<double> slice_spacing_mm;
  double z_offset_mm = 0.0;  // seg.z_offset_mm (needs seg.slice_spacing_mm)
};

struct RegisterOptions {
  bool enabled = true;
  std::string method = "phase+ecc";  // "phase", "phase+ecc", "none"
  double ecc_scale = 0.5;            // ECC refinement at this fraction of full resolution
  int ecc_iterations = 50;
  double jump_px = 6.0;  // an inter-slice motion above this is flagged as a jump
  // With CT, the output grid is the CT's frame at the colour resolution (docs/ARCHITECTURE.md
  // "The output frame"): CT pixel u lands on output q = c + s·R(rotation_deg)(u − c_ct) + d,
  // s = ct.pixel_spacing_mm[0] / spacing_mm[0]. This is that definition's rotation (degrees)
  // and shift (output pixels); default identity: axis-aligned, centre on centre.
  Rigid output_frame;
  // What ties the stack to a drift-free frame: "ct" (every colour slice aligned to its CT
  // slice), "fiducials" (tubes in the gel), "none" (slice-to-slice only: absolute drift is not
  // observable, the report says so) or "auto" (ct when configured, else fiducials when found,
  // else none).
  std::string anchor = "auto";
  // register.ct_anchor_between: the CT anchor of a colour slice that lies between two CT slices
  // (slice_z.h): "nearest" = aligned to the CT slice nearest in z, its confidence scaled by
  // 1 − 2·d/ct.slice_spacing_mm (d = the z distance, so 0 half-way: no anchor there);
  // "interpolated" = aligned to the CT interpolated linearly in HU to its z, full confidence.
  // docs/BENCHMARKS.md "CT at its own slice spacing" compares them.
  std::string ct_anchor_between = "nearest";
  std::string overrides;  // absolute path of the per-slice override file; empty = none
};

struct MaskOptions {
  double hu_threshold = -400.0;  // CT voxels above this are body (air/gel are below)
  int opening_px = 1;            // morphological opening radius on the colour grid
  bool refine_gel = true;        // refine the edge by distance to the gel colour
  std::optional<std::array<int, 3>> gel_colour;  // RGB of the gel; estimated when absent
  double gel_distance = 40.0;  // colour distance under which a boundary pixel counts as gel
  // Parts of a slice's body smaller than this (mm², in the slice's plane) are debris (outline.h,
  // the part rule). A finger is ~150 mm² across, its tip a few tens; the CT opening already
  // removes anything narrower than 2·kCtDetachPx + 1 CT pixels.
  double min_part_mm2 = 5.0;
};

struct PackOptions {
  int brick_edge = 64;  // power of two, 8..256
  int zstd_level = 3;   // 0 = raw bricks, 1..22
  int downsample = 1;   // integer factor applied to x and y of the output grid
  int threads = 0;      // 0 = all cores
  // What the packed file keeps outside the body (voxels whose work/mask/mask_NNNN.png is 0),
  // config key pack.keep_outside_body: "none" (default) stores colour (r, g, b) = 0 and CT =
  // −1024 HU (air) there, so that bricks of gel are uniform and cost nothing; "colour", "ct" or
  // "all" keep that channel as registered / resampled. Alpha and labels are never changed.
  bool keep_colour_outside_body = false;
  bool keep_ct_outside_body = false;
  // pack.crop_margin_px: when set (>= 0), x and y of the packed volume are cropped to the union
  // over the stack of the body masks' bounding boxes plus this margin in output-grid pixels
  // (before downsampling), clamped to the frame; origin_mm moves with the crop. Unset (default):
  // the whole registered frame is packed. z is never cropped.
  std::optional<int> crop_margin_px;
};

// What the stages write into the work folder besides what a person inspects (masks, overlays,
// label slices, transforms, QC), config section "work" (docs/ARCHITECTURE.md, 'Work folder
// layout'). The later stages never read the full-size registered colour or resampled CT back: they
// resample them from the input slices and transforms.json (work_layout.h), so these switches change
// only what is on disk.
struct WorkOptions {
  bool write_registered = false;  // <work>/register/registered/rgb_NNNN.png (full size)
  bool write_ct = false;          // <work>/mask/ct_NNNN.png (16-bit HU + 32768, full size)
  int overlay_max_px = 1024;      // <work>/mask/overlay_NNNN.png: longer side at most this
                                  // (downsampled by block mean); 0 = full size
};

// Config section "vdb" (the OpenVDB export, vdb.h). OpenVDB's writer takes whole in-memory
// grids, so the export's memory is bounded by `max_memory_mb` through its layout
// (docs/ARCHITECTURE.md "The OpenVDB export: one file or parts"): with layout "auto" the level
// (`level`, or 0) is written as one file when its estimate fits the budget, else as parts of
// consecutive z slabs, each within the budget, listed in "<vdb_output stem>.parts.json"; with
// layout "file" one file always, at `level` or else the finest level whose estimate fits (a set
// `level` over the budget is a ConfigError, not an export that might be killed).
enum class VdbLayout { kAuto, kFile };

struct VdbOptions {
  bool enabled = true;
  std::optional<int> level;  // vdb.level: 0 = the packed file's level 0; unset / "auto" = auto
  VdbLayout layout = VdbLayout::kAuto;  // vdb.layout: "auto" (default) or "file"
  // vdb.max_memory_mb: budget of the export (MiB), per file written. 1024 by default: a fixed
  // number, so the layout chosen (and the files written) do not depend on the machine, below the
  // streaming pass's own peak at 2048x1216 (about 1.1 GB), so the export never sets the run's
  // peak; the export's peak stays near it whatever the stack's length (the NLM male's level 0,
  // ~25 GB of grids, as about 28 parts).
  std::int64_t max_memory_mb = 1024;
};

struct Config {
  std::string path;  // the config file (absolute)
  std::string name;
  std::string work_dir;                             // absolute
  std::string output;                               // packed file, absolute
  std::string vdb_output;                           // absolute; empty = no export
  std::array<double, 3> spacing_mm{1.0, 1.0, 1.0};  // output grid (x, y, z) before downsampling
  SliceSource rgb;
  std::optional<CtSource> ct;
  std::optional<SegSource> seg;
  RegisterOptions registration;
  MaskOptions mask;
  PackOptions pack;
  WorkOptions work;
  VdbOptions vdb;
  nlohmann::json raw_json;  // the file as read, for hashing sections into reports
};

// The most errors one ConfigError lists line by line.
inline constexpr std::size_t kMaxConfigErrors = 20;

// Loads and validates a config file. Throws ConfigError (bad content: every error found, one line
// each, see above) or IoError (unreadable).
Config load_config(const std::string& path);

// The candidate nearest to `key` in spelling (optimal-string-alignment edit distance, case
// ignored; a candidate that starts with `key` counts as near), or "" when none is near enough to
// be the key meant: distance at most 2, or at most a third of the longer name.
std::string nearest_key(const std::string& key, const std::vector<std::string>& candidates);

// The config as JSON in the loader's schema: every key written with its value (defaults
// included), paths relative to `base_dir` (default: the folder of config.path; absolute paths
// are kept when no relative form exists). load_config of the written file gives back the same
// Config (raw_json aside). Pure; thread-safe.
nlohmann::json config_to_json(const Config& config);
nlohmann::json config_to_json(const Config& config, const std::string& base_dir);

// Writes config_to_json(config, folder of `path`) to `path` atomically (2-space indented JSON).
// Throws IoError when the file cannot be written.
void write_config(const std::string& path, const Config& config);

// Every key path the loader accepts ("ct.raw.width", ...), for documentation and the schema test.
// Keys starting with '_' are comments, accepted anywhere and ignored; JSON comments (// and /* */)
// are stripped by the parser.
std::vector<std::string> config_key_paths();

// Hash (16 hex digits) of the named parts of the config as written: top-level sections ("mask")
// or single keys inside them ("mask.hu_threshold"), absent ones hashing as null. Keys starting
// with '_' (comments) do not count. Used by stage manifests to decide whether outputs are stale:
// a stage lists exactly what it reads, so touching another key does not rerun it.
std::string config_section_hash(const Config& config, const std::vector<std::string>& sections);

}  // namespace vispack::pipeline

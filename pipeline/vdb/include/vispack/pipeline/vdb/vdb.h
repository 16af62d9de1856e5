// vispack-vdb: OpenVDB export of one level of the packed file (OpenVDB 10).
//
// Source: config.output (the .vpk that vispack-pack wrote), read with the format Reader, so the
// export holds what the packed volume holds (colour cleared and CT -1024 HU outside the body,
// crop and pack.downsample applied; levels >= 1 alpha-weighted colour, majority labels) and
// agrees with the viewer. Level and layout (plan_vdb_export, vdb_level.h; estimated before any
// grid is built): vdb.layout "auto" (default) exports vdb.level, or level 0, as one file when its
// estimate fits vdb.max_memory_mb, else as parts; vdb.layout "file" exports one file, of
// vdb.level or of the finest level whose estimate fits. Grids:
//   "ct"     FloatGrid, HU (the .vpk's int16 ct channel), when the file has "ct"
//   "labels" Int32Grid, label IDs (uint8 / uint16 "labels"), when the file has "labels"
//   "rgb"    Vec3SGrid, colour r/255, g/255, b/255 of the "rgba" channel
// Voxels are active where the packed alpha (body coverage) is > 0: at level 0 of an undownsampled
// file exactly the body mask of work/mask. Background: 0 (ct: -1024 HU). Index (i, j, k) =
// (x, y, z) of the level; the transform maps it to the level's origin_mm + (i, j, k) * spacing_mm
// (world coordinates in millimetres, anisotropic). Metadata on the file and on each grid:
// "vispack_version", "vispack_level" (int), "vispack_level_choice" ("auto" | "vdb.level"),
// "vispack_voxel_size_mm", "vispack_origin_mm" (vec3d), "vispack_source" (the .vpk's file name);
// per grid "units" ("HU", "id", "rgb01"). The stdout line (unless quiet) and work/vdb/report.json
// say the level, its estimate and the budget.
// The file is written with io::File's default compression (Blosc when OpenVDB has it, else zip)
// to a temporary name and renamed: config.vdb_output appears complete or not at all
// (vdb_write.h). Threads (--threads, vdb_level.h's estimate too): the grids are built from runs
// of bricks on every thread and merged (the trees equal a one-thread build when the brick edge
// is a multiple of 8, else one thread builds); with two or more, the file's write system calls
// run beside OpenVDB's serialisation.
// Shards (`--slices A:B`, a part of the stack): the part of the chosen level whose z lies in
// [ceil(A * D / S), ceil(B * D / S)) (D = the level's slice count, S = the stack's), written to
// vdb_part_path(config, A, B) ("<vdb_output stem>.slices-AAAA-BBBB.vdb" beside vdb_output)
// instead of vdb_output, with the same grids, transform and metadata plus "vispack_part_slices"
// ("A:B") and "vispack_part_z" (the level z range, "z0:z1"). The parts of any set of shards that
// tile the stack are disjoint and hold together exactly the voxels of the unsharded export (each
// grid of one part merges into the same grid of another: tree().merge()). Every shard chooses
// the same level (the choice reads the whole packed file). Resume per part: work/vdb-parts. On a
// cluster the parts run as one array job after the pack merge (scripts/vispack-slurm); the
// unsharded export (vispack-run, workflow/Snakefile) writes vdb_output. Needs vdb.enabled.
// Parts (layout "auto", the level over the budget as one file): consecutive z slabs of the level
// (plan_vdb_parts: whole brick rows while they fit, cut at multiples of 8 z so no leaf straddles
// two), each estimated within vdb.max_memory_mb, built and written one after another, each a
// complete file named and tagged as a shard's part (vdb_part_path of the stack slices it covers,
// "vispack_part_slices", "vispack_part_z"), and then the index vdb_parts_index_path(config)
// (JSON: level, dims, voxel size, origin, grids, the reason, and per part its file, slices, z
// range, active voxels, leaves, bytes); vdb_output itself is not written (an earlier one is
// removed, as are the parts an earlier index listed when one file is written). Merged (the
// grids of one name, tree().merge()), the parts hold exactly the voxels of the one-file export.
// The stdout line and the report ("layout", "layout_reason", "parts") say which and why.
// A shard (--slices A:B) plans the same export from the whole file (the plan follows from the
// packed file and the config): a level that fits as one file, it writes its slices' part of
// (above; report layout "shard part"); over the budget, the plan's parts whose first z lies in
// its level z range [ceil(A * D / S), ceil(B * D / S)) (each part one shard's; a shard may
// write none), each recorded in work/vdb-parts/part-<file>.json (plan key, index header, the
// part's index entry); the shard that finds every part recorded and present writes the index,
// the same bytes one process writes (report: layout "parts", "parts" its own, "parts_planned",
// "index_complete", "shard_z"). An index of another plan is removed before a shard writes.
// Memory: bounded by vdb.max_memory_mb per file written, whatever the stack's length (the
// packed file's pages are released after each brick is decoded; docs/BENCHMARKS.md).
#pragma once

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/stage_run.h"

namespace vispack::pipeline {

// Writes config.vdb_output. Throws ConfigError (vdb disabled; vdb.level absent from the file or
// over the budget; no level fits the budget), InputError (packed file missing, no rgba channel),
// FormatError (packed file defective), IoError.
StageResult run_vdb_stage(const Config& config, const StageOptions& options);

// The file a shard [first, last) of the stack is exported to: "<dir>/<stem>.slices-FFFF-LLLL.vdb"
// for vdb_output "<dir>/<stem>.vdb" (4 digits at least, zero-padded).
std::string vdb_part_path(const Config& config, int first, int last);

// The index of an export written as parts: "<dir>/<stem>.parts.json" for vdb_output
// "<dir>/<stem>.vdb".
std::string vdb_parts_index_path(const Config& config);

}  // namespace vispack::pipeline

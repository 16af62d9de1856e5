// vispack-vdb: OpenVDB export of one level of the packed file (OpenVDB 10).
//
// Source: config.output (the .vpk that vispack-pack wrote), read with the format Reader, so the
// export holds what the packed volume holds (colour cleared and CT -1024 HU outside the body,
// crop and pack.downsample applied; levels >= 1 alpha-weighted colour, majority labels) and
// agrees with the viewer. Level: config vdb.level, or the finest level whose estimated memory
// fits vdb.max_memory_mb (vdb_level.h; the estimate is made before any grid is built). Grids:
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
// to a temporary name and renamed: config.vdb_output appears complete or not at all.
// Not sharded (`--slices` with a partial range is a UsageError): one .vdb file holds whole grids
// that openvdb::io::File::write takes from memory. On a cluster it is one job after the pack merge
// (scripts/vispack-slurm, workflow/Snakefile). Needs vdb.enabled.
// Memory: bounded by vdb.max_memory_mb (measured against the estimate in docs/BENCHMARKS.md).
#pragma once

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/stage_run.h"

namespace vispack::pipeline {

// Writes config.vdb_output. Throws ConfigError (vdb disabled; vdb.level absent from the file or
// over the budget; no level fits the budget), InputError (packed file missing, no rgba channel),
// FormatError (packed file defective), IoError.
StageResult run_vdb_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

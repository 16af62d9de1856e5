// vispack-vdb: OpenVDB export of the pipeline intermediates (OpenVDB 10).
//
// Grids, at full resolution of the output grid (pack.downsample does not apply):
//   "ct"     FloatGrid, HU (from work/mask/ct_NNNN.png), only when the config has "ct"
//   "labels" Int32Grid, label IDs (work/labels/labels_NNNN.png), only when the config has "seg"
//   "rgb"    Vec3SGrid, colour in 0..1 (work/register/registered/rgb_NNNN.png)
// Voxels are active only inside the body mask (work/mask/mask_NNNN.png); the background value is
// 0 (ct: -1024 HU). Index (i, j, k) = (x, y, z) of the output grid; the transform is a scale
// by spacing_mm (anisotropic), so world coordinates are millimetres with voxel (0, 0, 0) at the
// origin. Grid class: ct and rgb GRID_FOG_VOLUME-like "unknown", labels unknown; each grid
// carries metadata "vispack_version" and "units" ("HU", "id", "rgb01").
// The file is written with io::File's default compression (Blosc when OpenVDB has it, else zip)
// to a temporary name and renamed: config.vdb_output appears complete or not at all.
// Not sharded (`--slices` with a partial range is a UsageError), on purpose: one .vdb file holds
// whole grids that openvdb::io::File::write takes from memory, so per-shard grids would have to
// be merged in one process anyway (a re-read of every shard's grids), and per-shard .vdb files
// would change what the export is (one file per volume). On a cluster it is one job after the
// pack merge (scripts/vispack-slurm, workflow/Snakefile), in parallel with nothing else; its cost
// is in docs/BENCHMARKS.md. Needs vdb.enabled.
#pragma once

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/stage_run.h"

namespace vispack::pipeline {

// Writes config.vdb_output. Throws ConfigError (vdb disabled), InputError (missing or wrong-sized
// intermediates), IoError.
StageResult run_vdb_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

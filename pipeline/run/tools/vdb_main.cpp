// vispack-vdb: see pipeline/vdb/vdb.h.
#include "vispack/pipeline/vdb/vdb.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-vdb", argc, argv,
      "Writes the OpenVDB export (config \"vdb_output\") of one pyramid level of the packed file "
      "(config \"output\", written by vispack-pack): FloatGrid ct (HU), Int32Grid labels, "
      "Vec3SGrid rgb (0..1), active where the packed alpha > 0, voxel size = the level's "
      "spacing. Level: vdb.level, or level 0. Memory: vdb.max_memory_mb (default 1024 MiB) "
      "per file: the level is written as one file when its estimate fits, else (vdb.layout "
      "\"auto\") as parts, consecutive z slabs each within the budget, in <vdb_output "
      "stem>.slices-AAAA-BBBB.vdb files listed in <vdb_output stem>.parts.json (merged, they "
      "hold exactly the one file's voxels); vdb.layout \"file\": one file always, of vdb.level "
      "or the finest level that fits (a vdb.level over the budget is a config error). Prints "
      "the level and the layout chosen and why (also in work/vdb/report.json and the files' "
      "metadata). With --slices A:B (a shard; every shard plans the same level and layout): "
      "a level that fits as one file, the part of it the stack slices [A, B) cover, written to "
      "<vdb_output stem>.slices-AAAA-BBBB.vdb (the parts of shards that tile the stack hold "
      "exactly the voxels of the one file); a level over the budget, the planned parts that "
      "start in those slices, and the shard that completes the set writes <vdb_output "
      "stem>.parts.json: the same files and index as one process writes.",
      vispack::pipeline::run_vdb_stage);
}

// vispack-vdb: see pipeline/vdb/vdb.h.
#include "vispack/pipeline/vdb/vdb.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-vdb", argc, argv,
      "Writes the OpenVDB export (config \"vdb_output\") of one pyramid level of the packed file "
      "(config \"output\", written by vispack-pack): FloatGrid ct (HU), Int32Grid labels, "
      "Vec3SGrid rgb (0..1), active where the packed alpha > 0, voxel size = the level's "
      "spacing. Level: vdb.level, or the finest whose estimated memory fits vdb.max_memory_mb "
      "(default 8192 MiB); a vdb.level over the budget is a config error. Prints the level "
      "chosen (also in work/vdb/report.json and the file's metadata). With --slices A:B (a "
      "shard): the part of that level the stack slices [A, B) cover, written to <vdb_output "
      "stem>.slices-AAAA-BBBB.vdb; the parts of shards that tile the stack hold exactly the "
      "voxels of the whole export.",
      vispack::pipeline::run_vdb_stage);
}

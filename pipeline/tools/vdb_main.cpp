// vispack-vdb: see pipeline/vdb.h.
#include "vispack/pipeline/vdb.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-vdb", argc, argv,
      "Writes the OpenVDB export (config \"vdb_output\"): FloatGrid ct (HU), Int32Grid labels, "
      "Vec3SGrid rgb (0..1), active inside the body mask, voxel size = spacing_mm. Not sharded.",
      vispack::pipeline::run_vdb_stage);
}

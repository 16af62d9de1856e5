// vispack-pack: see pipeline/pack.h.
#include "vispack/pipeline/pack.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-pack", argc, argv,
      "Builds the packed volume (config \"output\") from the intermediates: rgba = registered "
      "colour "
      "+ body mask as alpha, ct = HU, labels = IDs, with the label table, slice defects, "
      "registration quality and provenance in the metadata. Not sharded.",
      vispack::pipeline::run_pack_stage);
}

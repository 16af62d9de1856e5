// vispack-mask: body masks from the CT (colour-refined) on the registered colour grid.
#include "vispack/pipeline/mask/mask_stage.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-mask", argc, argv,
      "Thresholds the CT into a body mask (largest component, holes filled, a head-holder cut "
      "off), carries it onto the registered colour grid and trims gel at its edge by colour. "
      "Writes <work>/mask/mask_NNNN.png, overlay_NNNN.png (at most work.overlay_max_px) and "
      "report.json (and ct_NNNN.png, HU + 32768, with work.write_ct). Needs vispack-register's "
      "output.",
      vispack::pipeline::run_mask_stage);
}

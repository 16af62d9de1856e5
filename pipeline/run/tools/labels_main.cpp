// vispack-labels: segmentation slices -> label IDs on the output grid
// (pipeline/labels/labels_stage.h).
#include "vispack/pipeline/labels/labels_stage.h"

int main(int argc, char** argv) {
  return vispack::pipeline::stage_main(
      "vispack-labels", argc, argv,
      "Maps the segmentation slices (seg section of the config) to label IDs through the palette "
      "(exact colour first, then the nearest palette colour within seg.tolerance), resamples them "
      "onto the registered output grid by nearest neighbour, and writes "
      "<work>/labels/labels_NNNN.png (16-bit IDs) and report.json. Exit code 6 names the file and "
      "pixel of an out-of-tolerance colour in strict mode.",
      vispack::pipeline::run_labels_stage);
}

// vispack-run --plan, the dry run: what a run would do, and the inputs checked as far as one can
// without running (README.md "Your own data").
#pragma once

#include <string>
#include <vector>

#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline {

// One input folder as the dry run saw it.
struct PlannedInput {
  std::string name;  // "rgb", "ct" or "seg"
  int slices = 0;
  int width = 0, height = 0;  // of its first slice, in pixels
  std::string first, last;    // file names of the first and last slice
};

struct Plan {
  int slices = 0;                   // the colour stack
  std::vector<std::string> stages;  // the stages the config enables, in order
  // Stack slices per level-0 slab of the pack (pack.brick_edge); 0 when a colour file is missing
  // inside the stack: slabs are brick_edge output slices (slots) and then hold fewer files, so no
  // fixed count of stack slices makes whole slabs (scripts/cluster_plan.py then shards the stack
  // evenly and packs in a step of its own, which is right for any shard bounds).
  int pack_slab_slices = 0;
  std::vector<PlannedInput> inputs;
  std::vector<std::string> warnings;  // the z-extent warnings a run would give
};

// Lists every input folder and reads the first and the last slice of each (colour, CT,
// segmentation) with the config's raw layout, and runs the register stage's layout checks on the
// middle colour slice, so that a wrong raw size, layout or header, a file that is not an image,
// colour slices of two sizes, a CT missing a slice or covering too little of the stack, or a
// segmentation matched by number to too few colour slices fail here with the error (and exit
// code) the run would give. Reads at most seven slices; writes nothing.
Plan plan_run(const Config& config);

// The plan as vispack-run --plan prints it: "slices N", "stages ...", "pack_slab_slices E" (the
// lines scripts/cluster_plan.py reads), then one "input NAME ..." line per input folder.
std::string format_plan(const Plan& plan);

}  // namespace vispack::pipeline

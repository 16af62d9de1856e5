// Registration of the colour stack (vispack-register's algorithms; docs/GOALS.md §1, §2, §6;
// conventions in imaging/transforms.h and docs/ARCHITECTURE.md "Slice transforms" and
// "Registration").
//
// The modules, one job each:
//   register/frame.h      a slice prepared once: grey levels, anchor colour level, fiducials
//   register/pair.h       slice-to-slice estimates (phase correlation + ECC), per-slice records
//   register/ct_anchor.h  the CT anchor: colour slice k aligned to CT slice k (absolute)
//   register/solve.h      the global solve of all slices at once; overrides
//   register/qc.h         QC pictures: CT outline over the registered slice, transform curves
// The stage that runs them is register_stage.h. All functions here are thread-safe.
#pragma once

#include "vispack/pipeline/register/ct_anchor.h"
#include "vispack/pipeline/register/frame.h"
#include "vispack/pipeline/register/pair.h"
#include "vispack/pipeline/register/qc.h"
#include "vispack/pipeline/register/solve.h"

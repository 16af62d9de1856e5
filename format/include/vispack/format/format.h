// Umbrella header: the whole packed-volume API. Needs both vispack_format_reader and
// vispack_format_writer; a reader-only program includes reader.h (and summary.h) instead.
#pragma once

#include "vispack/format/downsample.h"
#include "vispack/format/findings.h"
#include "vispack/format/geometry.h"
#include "vispack/format/limits.h"
#include "vispack/format/metadata.h"
#include "vispack/format/reader.h"
#include "vispack/format/summary.h"
#include "vispack/format/types.h"
#include "vispack/format/writer.h"

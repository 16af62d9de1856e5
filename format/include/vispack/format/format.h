// Umbrella header: the whole packed-volume API (types, writer, reader, reduction rules).
#pragma once

#include "vispack/format/downsample.h"
#include "vispack/format/reader.h"
#include "vispack/format/types.h"
#include "vispack/format/writer.h"

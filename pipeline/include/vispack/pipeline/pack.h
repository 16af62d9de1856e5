// vispack-pack: the packed volume file from the pipeline intermediates (format/SPEC.md).
//
// Channels, on the output grid (the registered RGB grid, x and y divided by pack.downsample):
//   rgba   uint8 x 4: registered colour (work/register/registered/rgb_NNNN.png) with
//          alpha = body mask (work/mask/mask_NNNN.png, 0/255; with downsampling, the covered
//          fraction of the block times 255)
//   ct     int16 HU (work/mask/ct_NNNN.png, stored HU + 32768), only when the config has "ct"
//   labels uint16 IDs (work/labels/labels_NNNN.png), only when the config has "seg"; with
//          downsampling, the most frequent ID of each block (ties: smaller ID), never a blend
// Colour and CT are downsampled by the block mean (cv::INTER_AREA).
// Streaming: one slice of each channel is read, converted and appended at a time; the format
// Writer keeps one slab of brick_edge slices, so memory stays bounded by one brick row.
// Metadata ("extra"): label table (palette.json, or the IDs present when there is none), missing
// slice numbers (gaps in the rgb file numbering), black and duplicated slices and registration
// quality (from transforms.json), provenance (vispack version, config hash, input hashes: xxHash64
// of transforms.json, palette, id map and of the input slices' names and sizes). No timestamps:
// the same inputs and config give a byte-identical file.
// Sharding: not supported (the file is one stream); `--slices` with a partial range is a
// UsageError. A whole-stack pack is fast (the bricks are compressed in parallel).
// Up to date: pack is one unit whose input fingerprint covers every intermediate it reads and
// the "pack", "spacing_mm", "name" config sections; the output file's identity is recorded.
#pragma once

#include "vispack/pipeline/config.h"
#include "vispack/pipeline/stage_run.h"

namespace vispack::pipeline {

// Writes config.output. Throws InputError (a missing or wrong-sized intermediate, naming it),
// IoError, UsageError (a shard range).
StageResult run_pack_stage(const Config& config, const StageOptions& options);

}  // namespace vispack::pipeline

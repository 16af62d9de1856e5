// vispack-pack: the packed volume file from the pipeline intermediates (format/SPEC.md).
//
// Channels, on the output grid (the registered RGB grid, x and y divided by pack.downsample):
//   rgba   uint8 x 4: registered colour (work/register/registered/rgb_NNNN.png) with
//          alpha = body mask (work/mask/mask_NNNN.png, 0/255; with downsampling, the covered
//          fraction of the block times 255)
//   ct     int16 HU (work/mask/ct_NNNN.png, stored HU + 32768), only when the config has "ct"
//   labels uint16 IDs (work/labels/labels_NNNN.png), only when the config has "seg"; with
//          downsampling, the most frequent ID of each block (ties: smaller ID), never a blend
// Outside the body (mask 0) colour is stored as 0 and CT as −1024 HU unless pack.keep_outside_body
// says to keep them (read_intermediates in work_layout.h does it, for pack and vdb alike).
// Colour is downsampled by the mask-weighted block mean (a gel pixel never darkens or tints the
// tissue of its block; the plain mean where the block has no body), CT by the block mean
// (cv::INTER_AREA).
// Crop (pack.crop_margin_px set): x and y are cut to the union of the body masks' bounding boxes
// over the stack plus the margin, clamped to the frame, its corners moved outwards to multiples
// of the downsampling factor (so the cropped grid is a sub-box of the uncropped one); origin_mm
// moves by the box's corner; metadata extra.crop records margin, box (full-resolution output
// pixels: x, y, width, height) and the uncropped dims. The masks are read once more for it.
// Output z is the colour slot (slice_z.h): a colour file missing inside the stack is an empty
// slice at its own z (colour 0, alpha 0, labels 0, CT −1024 HU as outside the body: it has no
// transform and no mask, so no CT is interpolated into it; docs/ARCHITECTURE.md "Each input at
// its own z"), so the volume's depth is the slots the stack spans, its z spacing is the colour
// slice spacing throughout, and extra.slices lists the empty slices (missing_slices, missing_z).
// Streaming: one slice of each channel is read, converted and appended at a time; the format
// Writer keeps one level-0 slab of brick_edge slices and spills the coarser levels' slabs to a
// nameless scratch file (format/writer.h "Memory"), so peak memory is about one level-0 brick row
// plus ~150 MB, whatever the slice count (docs/BENCHMARKS.md "Pack memory against the slice
// count").
// Metadata ("extra"): label table (palette.json, or the IDs present when there is none), missing
// slice numbers and names (gaps in the rgb file numbering) and their output z, black and
// duplicated slices (output z) and registration quality (from transforms.json), provenance (vispack
// version, config hash, input hashes: xxHash64 of transforms.json, palette, id map and of the input
// slices' names and sizes). No timestamps: the same inputs and config give a byte-identical file.
// Sharding (format/SPEC.md "Partial slab files"): a shard `--slices A:B` (a partial range)
// encodes the level-0 slabs (brick rows of brick_edge output slices along z) whose FIRST slice
// lies in the range's output z [slot of A, slot of B) (A, B stack indices; the empty slots after a
// file belong to its range), so any partition of the stack into ranges partitions the slabs (a
// range holding no slab start does nothing). Each slab becomes <work>/pack-slabs/slab_NNNN.vpkslab
// (NNNN = bz), written atomically, recorded in the pack-slabs manifest (resume keeps finished
// slabs; --force redoes them). A slab file also carries the slab's level-1 slices (zstd).
// run_pack_merge then writes config.output from every slab file: level-0 payloads are copied as
// they are (never decoded or recompressed), the coarser levels are built from the level-1 slices,
// and the file is byte-identical to a whole-stack pack of the same intermediates (the one brick
// encoder and the same slab order: format/writer.h). A merge refuses a missing slab file, one
// written with other options, and one whose slices changed since (InputError naming the file and
// the --slices shard to rerun). The merge records the whole pack's input fingerprint, so a later
// whole pack (or vispack-run) finds the output up to date. Up to date: pack is one unit whose input
// fingerprint covers every intermediate it reads and the "pack", "spacing_mm", "name" config
// sections; the output file's identity is recorded.
#pragma once

#include <memory>
#include <vector>

#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/intermediates.h"
#include "vispack/pipeline/pack/pack_merge.h"

namespace vispack::pipeline {

// Writes config.output (whole stack) or the shard's slab files (options.slices a partial range).
// Throws InputError (a missing or wrong-sized intermediate, naming it), IoError, UsageError (a bad
// range).
StageResult run_pack_stage(const Config& config, const StageOptions& options);

// The pack fed from memory, one slice at a time in z order: the streaming vispack-run (stream.h).
// Whole stack (options.slices empty or the whole stack): same plan, per-slice conversion, Writer
// and pack manifest record as the whole-stack run_pack_stage, so the file is byte-identical and a
// later vispack-pack finds it up to date. A shard (options.slices = A:B, a partial range, whose
// slabs all end inside it: streamable(config, S, range)): the slices A, A+1, ... are appended;
// each slab whose first slice lies in [A, B) is gathered (one slab of brick_edge slices held) and,
// once complete, encoded and written as run_pack_stage's shard writes it (same slab file, same
// pack-slabs record; skipped when that slab file is up to date), ready for run_pack_merge.
// Thread-safety: convert() may be called concurrently; append() and finish() from one thread at a
// time. Destroyed without finish(), it leaves config.output untouched (the Writer's temporary is
// removed) and records nothing more (a shard keeps the slab files it finished).
class PackStream {
 public:
  // False where the plan needs every slice's intermediates before the first one is packed:
  // pack.crop_margin_px set (the box is the union of all body masks) or segmentation without a
  // palette (the label table is the labels stage report's "ids_present"). The streaming run then
  // writes masks and labels first and packs from the work folder (run_pack_stage).
  static bool streamable(const Config& config);
  // streamable(config) for the shard `range` (stack indices) of the placed colour stack `stack`:
  // also false when the range's output z (slots, slice_z.h colour_slots_of_stack_range) starts no
  // slab, or when its last slab ends after them (that slab needs another shard's slices: the
  // shard's pack then runs after every shard, as vispack-pack). Without a missing colour file the
  // output z of a stack slice is its index; with one, slabs of brick_edge output slices hold fewer
  // files and ranges aligned to brick_edge stack slices need not be whole slabs.
  static bool streamable(const Config& config, const std::vector<SliceFile>& stack,
                         SliceRange range);
  // Plans the pack and opens the Writer (whole stack) or the pack-slabs stage run (a shard).
  // Throws UsageError when not streamable (above); otherwise as run_pack_stage.
  PackStream(const Config& config, const StageOptions& options);
  ~PackStream();
  PackStream(const PackStream&) = delete;
  PackStream& operator=(const PackStream&) = delete;

  // One slice converted to the writer's buffers (opaque; deleted by pack.cpp).
  struct Slice;
  struct SliceDeleter {
    void operator()(Slice* slice) const;
  };
  using SlicePtr = std::unique_ptr<Slice, SliceDeleter>;
  // Converts the intermediates of one slice, as read_intermediates would return them (use
  // clear_outside_body), to the packed grid.
  SlicePtr convert(Intermediates in) const;
  // Appends the next slice (z order: the k-th call appends stack slice first + k, first = 0 or
  // the shard's A). A shard encodes and writes a slab when its last slice is appended: its masks
  // and labels must be written and recorded by then (the slab file's input fingerprint).
  void append(SlicePtr slice);
  // Whole stack: commits the file and records the pack unit with the input fingerprint of the
  // work folder as it is now (call it after every mask and label file is written and recorded).
  // A shard: writes its pack-slabs report. Throws std::logic_error unless every slice of the
  // range was appended.
  StageResult finish();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vispack::pipeline

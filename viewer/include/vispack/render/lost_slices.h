// Lost slices (docs/GOALS.md §1: black slices lost at block cuts) shown as missing, never as a
// black band. The packed file lists them (metadata extra.slices.black, level-0 z indices);
// LostSliceSource wraps a VolumeSource and, for the rgba channel only (CT and labels exist for
// those slices), replaces every lost slice by the linear interpolation of the nearest valid
// slices below and above it, so that trilinear sampling "samples across" the gap. Alpha is
// interpolated linearly and colour weighted by alpha (premultiplied colour stays linear). With
// a valid slice on one side only, that slice is copied; with none, the data is left as read.
// Display only: the file is never changed.
//
// Coarser levels: a level-L slice is lost when any level-0 slice it is reduced from is lost
// (its mean is darkened); it is interpolated from the nearest valid level-L slices the same way.
//
// Thread-safety: as the wrapped source (read_region may run on several threads at once).
#pragma once

#include <memory>
#include <mutex>
#include <vector>

#include "vispack/render/volume.h"

namespace vispack::render {

// Level-L slice indices that are lost, from the sorted level-0 list (nz_level = dims[2] of L).
std::vector<std::int64_t> lost_slices_at_level(const std::vector<std::int64_t>& lost0, int level,
                                               std::int64_t nz_level);

class LostSliceSource final : public VolumeSource {
 public:
  // `lost0`: level-0 slice indices (any order; out-of-range entries are ignored).
  LostSliceSource(std::shared_ptr<const VolumeSource> inner, std::vector<std::int64_t> lost0);
  std::string name() const override { return inner_->name(); }
  int level_count() const override { return inner_->level_count(); }
  LevelGeometry level(int level) const override { return inner_->level(level); }
  bool has_channel(Channel c) const override { return inner_->has_channel(c); }
  std::vector<Label> labels() const override { return inner_->labels(); }
  int brick_edge() const override { return inner_->brick_edge(); }
  void read_region(Channel c, int level, const Region& region, void* out) const override;
  // rgba bricks that hold a lost slice are recomputed from the filled data; the rest passes.
  BrickStats brick_stats(Channel c, int level,
                         const std::array<std::int64_t, 3>& brick) const override;
  std::vector<std::int64_t> lost_slices() const override { return lost_[0]; }

 private:
  bool is_lost(int level, std::int64_t z) const;
  std::shared_ptr<const VolumeSource> inner_;
  std::vector<std::vector<std::int64_t>> lost_;  // per level, sorted
  // brick_stats' brick buffer, kept between calls: a fresh megabyte per brick is returned to
  // the system and faulted in again at each call (allocator trimming), which cost the brick
  // tree half its time (docs/BENCHMARKS.md, 'Viewer on long files').
  mutable std::mutex scratch_mutex_;
  mutable std::vector<std::uint8_t> scratch_;
};

// Wraps `source` in a LostSliceSource when it lists lost slices; returns it unchanged otherwise.
std::shared_ptr<const VolumeSource> fill_lost_slices(std::shared_ptr<const VolumeSource> source);

}  // namespace vispack::render

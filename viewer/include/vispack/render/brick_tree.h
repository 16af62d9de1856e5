// Bricks paged by view (docs/BENCHMARKS.md, 'Viewer: bricks paged by view'): which bricks of which
// pyramid level a frame draws, in what order, and which can be skipped because they cannot
// contribute. No GL here; the GL brick cache (viewer/brick_cache.h) uploads what a plan asks for
// and the slice renderer draws it.
//
// The bricks of all levels form an octree: brick b of level L covers the level-0 voxels
// [b·e·2^L, (b + 1)·e·2^L) per axis (e = brick edge), i.e. bricks 2b and 2b + 1 of level L − 1.
// Every brick's world box is clipped to the level-0 box, so the boxes of a plan tile the volume
// without overlap whatever mix of levels it holds.
//
// Empty-space skipping is conservative: each brick carries the range of its level-0
// descendants (channel min/max, label sets from the file's index), widened by its 26 neighbours
// at its own level (a sample near a face interpolates the neighbour's border voxels, and
// gradients reach one voxel further). A brick is skipped only when no value in that range can
// give a visible sample under the mode and transfer function (may_contribute).
//
// Visibility order: children of a node are sorted back to front by the grid rule (per axis the
// distance, in cells, from the eye's cell; compared z, then y, then x, largest first), which is
// a valid visibility order for a grid of boxes, hence for the octree traversal.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <functional>
#include <vector>

#include "vispack/render/camera.h"
#include "vispack/render/transfer.h"
#include "vispack/render/volume.h"

namespace vispack::render {

struct BrickKey {
  int level = 0;
  std::array<std::int64_t, 3> brick{0, 0, 0};
  bool operator==(const BrickKey& o) const { return level == o.level && brick == o.brick; }
  bool operator!=(const BrickKey& o) const { return !(*this == o); }
};
struct BrickKeyHash {
  std::size_t operator()(const BrickKey& k) const {
    std::size_t h = std::size_t(k.level) * 0x9E3779B97F4A7C15ull;
    for (std::int64_t v : k.brick)
      h = (h ^ std::size_t(v)) * 0x100000001B3ull;
    return h;
  }
};

// Channel sets are bit masks: bit int(Channel).
constexpr unsigned channel_bit(Channel c) {
  return 1u << unsigned(c);
}
// The channels a frame in params.mode reads, among the `present` ones.
unsigned channels_for(const RenderParams& params, unsigned present);

// The values a box of voxels can produce (conservative: samples interpolate inside it).
struct ValueRange {
  int alpha_max = 0;                    // rgba: largest alpha (coverage)
  std::int64_t ct_min = 0, ct_max = 0;  // ct: HU
  std::vector<std::uint16_t> labels;    // labels: IDs present, sorted
  void merge(const ValueRange& o, bool first);
};
// False when no sample whose values lie in `r` can be visible under `params` (mip, average
// and mpr always true).
bool range_may_contribute(const ValueRange& r, const RenderParams& params);

// Sub-brick empty-space skipping: a brick's voxels cut into cells of `cell` voxels per side,
// each with the range of its voxels plus `border` voxels around it (from a bordered brick, so
// the range covers every voxel its samples and gradients read). The renderer draws only the
// cells that may contribute.
struct CellGrid {
  int cell = 16;
  std::array<std::int64_t, 3> dims{0, 0, 0};  // cells per axis
  std::vector<ValueRange> ranges;             // x fastest
  unsigned channels = 0;                      // channels accumulated so far
};
// Cell edge used for bricks of edge `brick_edge`: max(4, brick_edge / 4).
int cell_edge(int brick_edge);
// Adds channel `c` of one bordered brick (element (0,0,0) = brick voxel (−border)³; `size` =
// the brick's voxels per axis without border) to `grid` (sized on the first call).
void accumulate_cells(CellGrid& grid, Channel c, const std::uint8_t* data,
                      const std::array<std::int64_t, 3>& size, int border);

// How a BrickTree builds its ranges (docs/BENCHMARKS.md, 'Viewer on long files').
enum class TreeBuild {
  // Every level's ranges in the constructor (reads every brick's stats of level 0).
  kEager,
  // The constructor reads the stats of the coarsest level's bricks only (a constant handful:
  // the coarsest level fits one brick or a few) and ranges them by their own stats; the ranges
  // of every level (the eager ones) are built afterwards by build_step / build_all, in small
  // steps (across frames). Until complete(), plan_bricks plans the coarsest level only, which
  // its own stats range exactly (a drawn brick samples its own level's voxels). Once complete(),
  // the tree, hence every plan and image, is the eager one.
  kCoarseFirst,
};

class BrickTree {
 public:
  // Reads the stats of the bricks (from the file's index for a packed file; a lost-slice source
  // decodes the bricks its lost slices cross): every level's for kEager, the coarsest level's
  // for kCoarseFirst (see TreeBuild). The source must outlive the tree.
  // Thread-safety: none (one thread builds, plans and draws).
  explicit BrickTree(const VolumeSource& source, TreeBuild build = TreeBuild::kEager);

  const VolumeSource& source() const { return *source_; }
  int levels() const { return int(geometry_.size()); }
  int brick_edge() const { return edge_; }
  unsigned present_channels() const { return present_; }
  const LevelGeometry& level(int l) const { return geometry_.at(std::size_t(l)); }
  const std::array<std::int64_t, 3>& grid(int l) const { return grid_.at(std::size_t(l)); }
  Box3 volume_box() const { return geometry_[0].box(); }
  // World box of a brick, clipped to the level-0 box.
  Box3 brick_box(const BrickKey& key) const;
  // False when no sample in the brick can be visible under `params` (see the header comment).
  // Before complete(), a brick finer than the coarsest level answers true (unknown).
  bool may_contribute(const BrickKey& key, const RenderParams& params) const;
  // Texture bytes of one brick with `border` voxels on each side, for `channels`.
  std::int64_t brick_bytes(const BrickKey& key, unsigned channels, int border) const;
  std::int64_t brick_voxels(const BrickKey& key) const;

  // Whether every level's ranges are built (always true for kEager).
  bool complete() const { return complete_; }
  // Advances the build by at most `max_units` units of work (one unit: one level-0 brick's
  // stats, one coarser brick's union of its children, or one brick's dilation); returns
  // complete(). The total is about 1.3 units per level-0 brick for each of own and dilated.
  bool build_step(std::int64_t max_units);
  // Advances the build for about `seconds` of wall time (at least one unit); returns complete().
  bool build_for(double seconds);
  void build_all();
  // Share of the build done, in [0, 1] (1 once complete()).
  double build_progress() const {
    return complete_ ? 1.0 : double(units_done_) / double(std::max<std::int64_t>(units_total_, 1));
  }
  // Instrumentation: brick_stats calls made so far for bricks of level `level` (all channels).
  std::int64_t stats_reads(int level) const { return stats_reads_.at(std::size_t(level)); }

 private:
  using Range = ValueRange;
  std::size_t index(const BrickKey& k) const;
  Range read_own(const BrickKey& k);  // from the source's stats
  Range dilated(const std::vector<Range>& own, const BrickKey& k) const;
  void finish_build();

  const VolumeSource* source_;
  int edge_ = 1;
  unsigned present_ = 0;
  std::vector<LevelGeometry> geometry_;
  std::vector<std::array<std::int64_t, 3>> grid_;
  std::vector<std::vector<Range>> ranges_;  // per level, dilated (before complete(): coarsest)
  std::vector<std::int64_t> stats_reads_;   // per level
  bool complete_ = false;
  // The build in progress: `own_` per level (level 0 from the stats, coarser levels the union
  // of their children), then `dilated_` per level; phase 0 fills own_, phase 1 dilated_, each
  // level by level from 0, brick by brick (`cursor_`, the linear brick index).
  std::vector<std::vector<Range>> own_, dilated_;
  int phase_ = 0, build_level_ = 0;
  std::int64_t cursor_ = 0, units_done_ = 0, units_total_ = 0;
};

struct PlanOptions {
  int finest_level = 0;
  int coarsest_level = -1;  // -1: the file's coarsest
  // A brick is refined while its level's smallest spacing covers more than this many pixels at
  // its nearest point (1: the level whose voxel size matches the screen footprint; larger while
  // moving).
  double lod_pixels = 1.0;
  // > 0: lod_pixels is doubled until the texture bytes of the drawn bricks fit.
  std::int64_t max_bytes = 0;
  int border = 2;  // voxels of border each brick texture carries (for the byte count)
};

struct BrickPlan {
  std::vector<BrickKey> draw;       // back to front
  std::vector<BrickKey> missing;    // wanted but not resident: coarsest first, then nearest first
  std::int64_t skipped = 0;         // bricks (octree nodes) that cannot contribute: not drawn
  std::int64_t skipped_voxels = 0;  // their voxels at their level
  std::int64_t culled = 0;          // outside the view frustum (or the mpr / clip plane)
  std::int64_t bytes = 0;           // texture bytes of `draw` (with borders)
  double lod_pixels = 1.0;          // used (after coarsening for max_bytes)
};

// Whether a brick is on the GPU with every channel the frame needs.
using ResidentFn = std::function<bool(const BrickKey&)>;

// Plans one frame. Without `resident` every brick counts as resident (the ideal plan). With it,
// a brick is refined only when all its children that the frame needs are resident (the others
// are listed in `missing`), so the drawn set always tiles the visible volume: coarse bricks
// first, refined as finer ones arrive. While the tree is not complete() only its coarsest level
// is planned (whatever the options' levels).
BrickPlan plan_bricks(const BrickTree& tree, const Camera& camera, const RenderParams& params,
                      const PlanOptions& options, unsigned channels,
                      const ResidentFn& resident = {});

}  // namespace vispack::render

// Where the viewer's voxels come from: a VolumeSource (a packed file, or memory in tests), and
// VolumeData, one level of a volume held in memory for the CPU reference ray caster.
//
// Coordinates follow docs/ARCHITECTURE.md: voxel (x, y, z) of a level has its centre at
// origin_mm + (x, y, z)·spacing_mm; buffers are x fastest, then y, then z.
// Channels as the viewer sees them (whatever the file stores):
//   Rgba   : 4 × uint8 per voxel, straight (not premultiplied) colour, alpha = body coverage
//   Ct     : int16 Hounsfield units
//   Labels : uint16 IDs (a uint8 label channel is widened), 0 = unlabelled
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "vispack/render/math.h"
#include "vispack/render/slicing.h"

namespace vispack::render {

enum class Channel { kRgba = 0, kCt = 1, kLabels = 2 };
constexpr int kChannelCount = 3;
const char* channel_name(Channel c);  // "rgba", "ct", "labels"
// Bytes per voxel in the viewer's layout above (4, 2, 2).
int channel_bytes(Channel c);

// One row of the label table (from the file's metadata).
struct Label {
  std::uint32_t id = 0;
  std::string name;
  std::array<std::uint8_t, 3> colour{0, 0, 0};  // sRGB
};

// Geometry of one level.
struct LevelGeometry {
  std::array<std::int64_t, 3> dims{0, 0, 0};
  Vec3 spacing_mm{1, 1, 1};
  Vec3 origin_mm{0, 0, 0};
  std::int64_t voxels() const { return dims[0] * dims[1] * dims[2]; }
  Box3 box() const { return volume_box(dims.data(), spacing_mm, origin_mm); }
};

// A box of voxels [x0, x0 + nx) × [y0, y0 + ny) × [z0, z0 + nz) of one level.
struct Region {
  std::array<std::int64_t, 3> offset{0, 0, 0};
  std::array<std::int64_t, 3> size{0, 0, 0};
  std::int64_t voxels() const { return size[0] * size[1] * size[2]; }
};

// Statistics of one brick over its valid voxels (the file's brick index, or computed):
// min/max per component (rgba: r, g, b, a; scalar channels use element 0), and for the labels
// channel the sorted IDs present. Used for empty-space skipping (brick_tree.h).
struct BrickStats {
  std::array<std::int64_t, 4> min{0, 0, 0, 0};
  std::array<std::int64_t, 4> max{0, 0, 0, 0};
  std::vector<std::uint32_t> labels;
};

// Read access to a multi-level volume. Level 0 is the finest; level_count() - 1 the coarsest.
// Thread-safety: read_region may be called from several threads at once (the loader decodes
// bricks on worker threads); the other members are const and cheap.
class VolumeSource {
 public:
  virtual ~VolumeSource() = default;
  virtual std::string name() const = 0;  // for error messages (a path, or "memory")
  virtual int level_count() const = 0;
  // Throws std::out_of_range for a bad level.
  virtual LevelGeometry level(int level) const = 0;
  virtual bool has_channel(Channel c) const = 0;
  virtual std::vector<Label> labels() const = 0;
  // Natural read granularity (the file's brick edge); the loader reads regions of this size.
  virtual int brick_edge() const = 0;
  // Copies `region` of channel `c` at `level` into `out` (region.voxels()·channel_bytes(c)
  // bytes, layout above). Throws std::out_of_range if the region leaves the level or the
  // channel is absent, FormatError (naming the file and brick) if stored data is corrupt.
  virtual void read_region(Channel c, int level, const Region& region, void* out) const = 0;
  // Statistics of brick `brick` (coordinates in the level's brick grid, brick_grid()) of channel
  // `c`. The default reads the brick and computes them; PackedSource answers from the index.
  // Throws std::out_of_range like read_region.
  virtual BrickStats brick_stats(Channel c, int level,
                                 const std::array<std::int64_t, 3>& brick) const;
  // Level-0 slice indices (z) whose colour is lost (black slices listed in the file's metadata,
  // extra.slices.black). Display only: the viewer samples across them (lost_slices.h).
  virtual std::vector<std::int64_t> lost_slices() const { return {}; }
};

// The statistics of `voxels` voxels of channel `c` in the viewer's layout (what the default
// VolumeSource::brick_stats computes from a brick it reads).
BrickStats compute_brick_stats(Channel c, const std::uint8_t* data, std::size_t voxels);

// Brick grid of a level: ceil(dims / brick_edge) per axis.
std::array<std::int64_t, 3> brick_grid(const VolumeSource& source, int level);
// The voxels of one brick of a level: [b·edge, min((b + 1)·edge, dims)) per axis.
Region brick_region(const VolumeSource& source, int level,
                    const std::array<std::int64_t, 3>& brick);

// One level of a volume in memory (straight RGBA, HU, label IDs). Absent channels are empty.
struct VolumeData {
  LevelGeometry geometry;
  std::vector<std::uint8_t> rgba;     // 4 per voxel
  std::vector<std::int16_t> ct;       // 1 per voxel
  std::vector<std::uint16_t> labels;  // 1 per voxel
  std::vector<Label> label_table;

  bool has(Channel c) const {
    return c == Channel::kRgba ? !rgba.empty()
                               : (c == Channel::kCt ? !ct.empty() : !labels.empty());
  }
  std::int64_t index(std::int64_t x, std::int64_t y, std::int64_t z) const {
    return x + geometry.dims[0] * (y + geometry.dims[1] * z);
  }
};

// Reads a whole level of every present channel. Memory: the level's full size (use for the
// reference ray caster and tests, not for the viewer's upload path).
VolumeData load_level(const VolumeSource& source, int level);

// A VolumeSource over VolumeData held in memory: one level, bricks of `brick_edge`.
class MemorySource final : public VolumeSource {
 public:
  explicit MemorySource(std::shared_ptr<const VolumeData> data, int brick_edge = 32);
  std::string name() const override { return "memory"; }
  int level_count() const override { return 1; }
  LevelGeometry level(int level) const override;
  bool has_channel(Channel c) const override { return data_->has(c); }
  std::vector<Label> labels() const override { return data_->label_table; }
  int brick_edge() const override { return brick_edge_; }
  void read_region(Channel c, int level, const Region& region, void* out) const override;

 private:
  std::shared_ptr<const VolumeData> data_;
  int brick_edge_;
};

// Opens a packed volume file (format/SPEC.md) through the memory-mapped format reader.
// Throws IoError / FormatError from the reader (naming the file).
std::unique_ptr<VolumeSource> open_packed(const std::string& path);

}  // namespace vispack::render

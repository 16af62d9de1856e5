#include "vispack/render/brick_tree.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>

#include "vispack/common/math_constants.h"
#include "vispack/render/reference.h"

namespace vispack::render {

unsigned channels_for(const RenderParams& p, unsigned present) {
  const unsigned rgba = channel_bit(Channel::kRgba), ct = channel_bit(Channel::kCt),
                 labels = channel_bit(Channel::kLabels);
  unsigned want = 0;
  switch (p.mode) {
    case Mode::kColour:
      want = rgba | (p.opacity_source == OpacitySource::kCt ? ct : 0u);
      break;
    case Mode::kCt:
    case Mode::kMip:
    case Mode::kAverage:
    case Mode::kIso:
    case Mode::kTf2d:
      want = ct;
      break;
    case Mode::kLabels:
      want = labels;
      if (p.label_shading != LabelShading::kFlat) want |= (present & ct) ? ct : rgba;
      break;
    case Mode::kMpr:
      want = (present & rgba) ? rgba : ct;
      break;
  }
  return want & present;
}

namespace {

void merge_labels(std::vector<std::uint16_t>& into, const std::vector<std::uint16_t>& add) {
  if (add.empty()) return;
  std::vector<std::uint16_t> out;
  out.reserve(into.size() + add.size());
  std::set_union(into.begin(), into.end(), add.begin(), add.end(), std::back_inserter(out));
  into.swap(out);
}

}  // namespace

BrickTree::BrickTree(const VolumeSource& source, TreeBuild build)
    : source_(&source), edge_(std::max(1, source.brick_edge())) {
  const int levels = source.level_count();
  if (levels < 1) throw std::invalid_argument(source.name() + ": no levels");
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
    if (source.has_channel(c)) present_ |= channel_bit(c);
  for (int l = 0; l < levels; ++l) {
    geometry_.push_back(source.level(l));
    grid_.push_back(brick_grid(source, l));
  }
  stats_reads_.assign(std::size_t(levels), 0);
  ranges_.resize(std::size_t(levels));
  own_.resize(std::size_t(levels));
  dilated_.resize(std::size_t(levels));
  for (int l = 0; l < levels; ++l) {
    const auto& g = grid_[std::size_t(l)];
    own_[std::size_t(l)].resize(std::size_t(g[0] * g[1] * g[2]));
    units_total_ += 2 * g[0] * g[1] * g[2];  // own, then dilated
  }
  if (build == TreeBuild::kCoarseFirst && levels > 1) {
    // The coarsest level ranged by its own bricks' stats: what a frame of that level samples.
    const int top = levels - 1;
    const auto& g = grid_[std::size_t(top)];
    std::vector<Range> own(std::size_t(g[0] * g[1] * g[2]));
    for (std::size_t i = 0; i < own.size(); ++i) {
      const std::int64_t n = std::int64_t(i);
      own[i] = read_own({top, {n % g[0], (n / g[0]) % g[1], n / (g[0] * g[1])}});
    }
    auto& out = ranges_[std::size_t(top)];
    out.resize(own.size());
    for (std::size_t i = 0; i < own.size(); ++i) {
      const std::int64_t n = std::int64_t(i);
      out[i] = dilated(own, {top, {n % g[0], (n / g[0]) % g[1], n / (g[0] * g[1])}});
    }
    return;
  }
  build_all();
}

BrickTree::Range BrickTree::read_own(const BrickKey& k) {
  Range r;
  const int l = k.level;
  ++stats_reads_[std::size_t(l)];
  if (present_ & channel_bit(Channel::kRgba))
    r.alpha_max = int(source_->brick_stats(Channel::kRgba, l, k.brick).max[3]);
  if (present_ & channel_bit(Channel::kCt)) {
    BrickStats s = source_->brick_stats(Channel::kCt, l, k.brick);
    r.ct_min = s.min[0];
    r.ct_max = s.max[0];
  }
  if (present_ & channel_bit(Channel::kLabels))
    for (std::uint32_t id : source_->brick_stats(Channel::kLabels, l, k.brick).labels)
      if (id < 65536) r.labels.push_back(std::uint16_t(id));
  return r;
}

// Dilation by the 26 neighbours at the same level.
BrickTree::Range BrickTree::dilated(const std::vector<Range>& own, const BrickKey& k) const {
  const auto& g = grid_[std::size_t(k.level)];
  const std::int64_t bx = k.brick[0], by = k.brick[1], bz = k.brick[2];
  Range r = own[index(k)];
  for (std::int64_t z = std::max<std::int64_t>(bz - 1, 0); z <= std::min(bz + 1, g[2] - 1); ++z)
    for (std::int64_t y = std::max<std::int64_t>(by - 1, 0); y <= std::min(by + 1, g[1] - 1); ++y)
      for (std::int64_t x = std::max<std::int64_t>(bx - 1, 0); x <= std::min(bx + 1, g[0] - 1);
           ++x) {
        const Range& n = own[index({k.level, {x, y, z}})];
        r.alpha_max = std::max(r.alpha_max, n.alpha_max);
        r.ct_min = std::min(r.ct_min, n.ct_min);
        r.ct_max = std::max(r.ct_max, n.ct_max);
        merge_labels(r.labels, n.labels);
      }
  return r;
}

bool BrickTree::build_step(std::int64_t max_units) {
  const int levels = int(geometry_.size());
  for (std::int64_t done = 0; !complete_ && done < std::max<std::int64_t>(max_units, 1); ++done) {
    const int l = build_level_;
    const auto& g = grid_[std::size_t(l)];
    const std::int64_t count = g[0] * g[1] * g[2];
    const BrickKey k{l, {cursor_ % g[0], (cursor_ / g[0]) % g[1], cursor_ / (g[0] * g[1])}};
    if (phase_ == 0) {
      // Own ranges: level 0 from the stats, coarser levels as the union of their children.
      Range& r = own_[std::size_t(l)][std::size_t(cursor_)];
      if (l == 0) {
        r = read_own(k);
      } else {
        const auto& gc = grid_[std::size_t(l - 1)];
        bool first = true;
        for (int c = 0; c < 8; ++c) {
          std::array<std::int64_t, 3> b{2 * k.brick[0] + (c & 1), 2 * k.brick[1] + ((c >> 1) & 1),
                                        2 * k.brick[2] + ((c >> 2) & 1)};
          if (b[0] >= gc[0] || b[1] >= gc[1] || b[2] >= gc[2]) continue;
          r.merge(own_[std::size_t(l - 1)][index({l - 1, b})], first);
          first = false;
        }
      }
    } else {
      auto& out = dilated_[std::size_t(l)];
      if (out.empty()) out.resize(std::size_t(count));
      out[std::size_t(cursor_)] = dilated(own_[std::size_t(l)], k);
    }
    ++units_done_;
    if (++cursor_ < count) continue;
    cursor_ = 0;
    if (++build_level_ < levels) continue;
    build_level_ = 0;
    if (++phase_ == 2) finish_build();
  }
  return complete_;
}

bool BrickTree::build_for(double seconds) {
  using clock = std::chrono::steady_clock;
  const auto end = clock::now() + std::chrono::duration<double>(std::max(seconds, 0.0));
  do
    build_step(64);
  while (!complete_ && clock::now() < end);
  return complete_;
}

void BrickTree::build_all() {
  while (!build_step(std::int64_t(1) << 20)) {
  }
}

void BrickTree::finish_build() {
  ranges_.swap(dilated_);
  dilated_.clear();
  own_.clear();
  own_.shrink_to_fit();
  complete_ = true;
}

std::size_t BrickTree::index(const BrickKey& k) const {
  const auto& g = grid_.at(std::size_t(k.level));
  for (int a = 0; a < 3; ++a)
    if (k.brick[a] < 0 || k.brick[a] >= g[a])
      throw std::out_of_range(source_->name() + ": brick outside the level's grid");
  return std::size_t(k.brick[0] + g[0] * (k.brick[1] + g[1] * k.brick[2]));
}

Box3 BrickTree::brick_box(const BrickKey& key) const {
  const LevelGeometry& g = level(key.level);
  Box3 b;
  for (int a = 0; a < 3; ++a) {
    std::int64_t v0 = key.brick[a] * edge_, v1 = std::min((key.brick[a] + 1) * edge_, g.dims[a]);
    b.lo[a] = g.origin_mm[a] + (double(v0) - 0.5) * g.spacing_mm[a];
    b.hi[a] = g.origin_mm[a] + (double(v1) - 0.5) * g.spacing_mm[a];
  }
  Box3 v = volume_box();
  b.lo = max(b.lo, v.lo);
  b.hi = min(b.hi, v.hi);
  return b;
}

std::int64_t BrickTree::brick_voxels(const BrickKey& key) const {
  const LevelGeometry& g = level(key.level);
  std::int64_t n = 1;
  for (int a = 0; a < 3; ++a)
    n *= std::min((key.brick[a] + 1) * edge_, g.dims[a]) - key.brick[a] * edge_;
  return n;
}

std::int64_t BrickTree::brick_bytes(const BrickKey& key, unsigned channels, int border) const {
  const LevelGeometry& g = level(key.level);
  std::int64_t n = 1;
  for (int a = 0; a < 3; ++a)
    n *= std::min((key.brick[a] + 1) * edge_, g.dims[a]) - key.brick[a] * edge_ + 2 * border;
  std::int64_t bpv = 0;
  for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels})
    if (channels & channel_bit(c)) bpv += channel_bytes(c);
  return n * bpv;
}

bool BrickTree::may_contribute(const BrickKey& key, const RenderParams& p) const {
  const std::vector<Range>& ranges = ranges_.at(std::size_t(key.level));
  if (ranges.empty()) return true;  // not built yet (kCoarseFirst, a finer level)
  return range_may_contribute(ranges[index(key)], p);
}

void ValueRange::merge(const ValueRange& o, bool first) {
  alpha_max = std::max(alpha_max, o.alpha_max);
  ct_min = first ? o.ct_min : std::min(ct_min, o.ct_min);
  ct_max = first ? o.ct_max : std::max(ct_max, o.ct_max);
  merge_labels(labels, o.labels);
}

bool range_may_contribute(const ValueRange& r, const RenderParams& p) {
  const bool opaque_scale = p.opacity > 0;
  auto window_positive = [&](double hu_max) {  // window01(hu) > 0 for some hu <= hu_max
    if (!(p.window_width_hu > 0)) return hu_max >= p.window_center_hu;
    return hu_max > p.window_center_hu - 0.5 * p.window_width_hu;
  };
  switch (p.mode) {
    case Mode::kColour:
      if (!opaque_scale) return false;
      return p.opacity_source == OpacitySource::kCt ? window_positive(double(r.ct_max))
                                                    : r.alpha_max > 0;
    case Mode::kCt:
      return opaque_scale && window_positive(double(r.ct_max));
    case Mode::kIso:
      return double(r.ct_max) >= p.iso_hu;
    case Mode::kTf2d:
      return opaque_scale && p.tf2d.any_opacity(double(r.ct_min), double(r.ct_max));
    case Mode::kLabels: {
      if (!opaque_scale) return false;
      for (std::uint16_t id : r.labels) {
        if (id == 0) continue;
        double f = (p.highlight_label >= 0 && int(id) != p.highlight_label) ? p.dim_factor : 1.0;
        double a = id < p.label_colours.size() ? double(p.label_colours[id].a) : 1.0;
        if (a * f > 0) return true;
      }
      return false;
    }
    case Mode::kMip:
    case Mode::kAverage:
    case Mode::kMpr:
      return true;
  }
  return true;
}

int cell_edge(int brick_edge) {
  return std::max(4, brick_edge / 4);
}

void accumulate_cells(CellGrid& grid, Channel c, const std::uint8_t* data,
                      const std::array<std::int64_t, 3>& size, int border) {
  const std::int64_t cell = grid.cell;
  if (grid.ranges.empty()) {
    for (int a = 0; a < 3; ++a)
      grid.dims[a] = (size[a] + cell - 1) / cell;
    grid.ranges.assign(std::size_t(grid.dims[0] * grid.dims[1] * grid.dims[2]), ValueRange{});
  }
  const bool first = (grid.channels & channel_bit(c)) == 0;
  if (!first) return;
  grid.channels |= channel_bit(c);
  const std::int64_t bx = size[0] + 2 * border, by = size[1] + 2 * border;
  const std::size_t bpv = std::size_t(channel_bytes(c));
  for (std::int64_t k = 0; k < grid.dims[2]; ++k)
    for (std::int64_t j = 0; j < grid.dims[1]; ++j)
      for (std::int64_t i = 0; i < grid.dims[0]; ++i) {
        ValueRange& r = grid.ranges[std::size_t(i + grid.dims[0] * (j + grid.dims[1] * k))];
        // Bordered coordinates of the cell's voxels and their border.
        const std::int64_t x0 = i * cell, x1 = std::min((i + 1) * cell, size[0]) + 2 * border;
        const std::int64_t y0 = j * cell, y1 = std::min((j + 1) * cell, size[1]) + 2 * border;
        const std::int64_t z0 = k * cell, z1 = std::min((k + 1) * cell, size[2]) + 2 * border;
        std::int64_t lo = std::numeric_limits<std::int64_t>::max(),
                     hi = std::numeric_limits<std::int64_t>::min();
        std::vector<bool> seen;
        for (std::int64_t z = z0; z < z1; ++z)
          for (std::int64_t y = y0; y < y1; ++y) {
            const std::uint8_t* row = data + bpv * std::size_t(x0 + bx * (y + by * z));
            for (std::int64_t x = x0; x < x1; ++x, row += bpv) {
              if (c == Channel::kRgba) {
                hi = std::max<std::int64_t>(hi, row[3]);
              } else if (c == Channel::kCt) {
                std::int16_t v;
                std::memcpy(&v, row, 2);
                lo = std::min<std::int64_t>(lo, v);
                hi = std::max<std::int64_t>(hi, v);
              } else {
                std::uint16_t v;
                std::memcpy(&v, row, 2);
                if (seen.empty()) seen.assign(65536, false);
                seen[v] = true;
              }
            }
          }
        if (c == Channel::kRgba) r.alpha_max = int(hi);
        if (c == Channel::kCt) {
          r.ct_min = lo;
          r.ct_max = hi;
        }
        if (c == Channel::kLabels)
          for (std::size_t id = 0; id < seen.size(); ++id)
            if (seen[id]) r.labels.push_back(std::uint16_t(id));
      }
}

namespace {

struct Planner {
  const BrickTree& tree;
  const Camera& cam;
  const RenderParams& params;
  unsigned channels;
  int finest, coarsest, border;
  double lod;
  const ResidentFn* resident;
  Mat4 vp;
  Vec3 eye_point;  // the eye (perspective) or a point far behind it (orthographic)
  double tan_half;
  BrickPlan plan;

  bool outside(const Box3& b) const {
    Vec4 c[8];
    for (int i = 0; i < 8; ++i) {
      Vec3 p = b.corner(i);
      c[i] = vp * Vec4{p.x, p.y, p.z, 1.0};
    }
    auto all = [&](auto pred) {
      for (int i = 0; i < 8; ++i)
        if (!pred(c[i])) return false;
      return true;
    };
    if (all([](const Vec4& v) { return v.x > v.w; }) ||
        all([](const Vec4& v) { return v.x < -v.w; }) ||
        all([](const Vec4& v) { return v.y > v.w; }) ||
        all([](const Vec4& v) { return v.y < -v.w; }) ||
        all([](const Vec4& v) { return v.z > v.w; }) ||
        all([](const Vec4& v) { return v.z < -v.w; }))
      return true;
    if (params.mode == Mode::kMpr) {  // only bricks the plane cuts
      double d = dot(cam.forward, params.mpr_target + cam.forward * params.mpr_offset_mm);
      int below = 0, above = 0;
      for (int i = 0; i < 8; ++i)
        (dot(cam.forward, b.corner(i)) < d ? below : above)++;
      if (below == 0 || above == 0) return true;
    }
    if (params.clip) {  // entirely on the removed side of the clip plane
      bool all_removed = true;
      for (int i = 0; i < 8; ++i)
        if (!(dot(params.clip_normal, b.corner(i)) > params.clip_d)) all_removed = false;
      if (all_removed) return true;
    }
    return false;
  }

  bool too_coarse(const BrickKey& k, const Box3& b) const {
    const Vec3 s = tree.level(k.level).spacing_mm;
    const double smin = std::min({s.x, s.y, s.z});
    double pixel;
    if (cam.orthographic) {
      pixel = 2.0 * cam.ortho_half_height / std::max(cam.height, 1);
    } else {
      double zmin = 1e300;
      for (int i = 0; i < 8; ++i)
        zmin = std::min(zmin, dot(b.corner(i) - cam.eye, cam.forward));
      // The nearest point of the box may be nearer than every corner (eye beside a face).
      Vec3 q = max(b.lo, min(cam.eye, b.hi));
      zmin = std::min(zmin, std::max(dot(q - cam.eye, cam.forward), 0.0));
      zmin = std::max(zmin, cam.near_mm);
      pixel = 2.0 * zmin * tan_half / std::max(cam.height, 1);
    }
    return smin > pixel * lod;
  }

  // Back-to-front order of bricks of one level (grid rule, see brick_tree.h).
  void order(int level, std::vector<BrickKey>& keys) const {
    const LevelGeometry& g = tree.level(level);
    const Box3 box = g.box();
    double e_cell[3];
    for (int a = 0; a < 3; ++a) {
      double cell = tree.brick_edge() * g.spacing_mm[a];
      e_cell[a] = std::floor((eye_point[a] - box.lo[a]) / cell);
    }
    auto key = [&](const BrickKey& k, int a) { return std::fabs(double(k.brick[a]) - e_cell[a]); };
    std::stable_sort(keys.begin(), keys.end(), [&](const BrickKey& x, const BrickKey& y) {
      for (int a = 2; a >= 0; --a) {
        double kx = key(x, a), ky = key(y, a);
        if (kx != ky) return kx > ky;
      }
      return false;
    });
  }

  bool is_resident(const BrickKey& k) const { return !resident || !*resident || (*resident)(k); }

  void visit(const BrickKey& k) {
    const Box3 box = tree.brick_box(k);
    if (outside(box)) {
      plan.culled++;
      return;
    }
    if (!tree.may_contribute(k, params)) {
      plan.skipped++;
      plan.skipped_voxels += tree.brick_voxels(k);
      return;
    }
    if (k.level > finest && (k.level > coarsest || too_coarse(k, box))) {
      std::vector<BrickKey> kids;
      const auto& g = tree.grid(k.level - 1);
      for (int i = 0; i < 8; ++i) {
        BrickKey c{k.level - 1,
                   {2 * k.brick[0] + (i & 1), 2 * k.brick[1] + ((i >> 1) & 1),
                    2 * k.brick[2] + ((i >> 2) & 1)}};
        if (c.brick[0] < g[0] && c.brick[1] < g[1] && c.brick[2] < g[2]) kids.push_back(c);
      }
      order(k.level - 1, kids);
      bool all_resident = true;
      for (const BrickKey& c : kids)
        if (!is_resident(c) && !outside(tree.brick_box(c)) && tree.may_contribute(c, params)) {
          all_resident = false;
          plan.missing.push_back(c);
        }
      if (all_resident) {
        for (const BrickKey& c : kids)
          visit(c);
        return;
      }
    }
    plan.draw.push_back(k);
    plan.bytes += tree.brick_bytes(k, channels, border);
  }

  void run() {
    std::vector<BrickKey> roots;
    const auto& g = tree.grid(coarsest);
    for (std::int64_t z = 0; z < g[2]; ++z)
      for (std::int64_t y = 0; y < g[1]; ++y)
        for (std::int64_t x = 0; x < g[0]; ++x)
          roots.push_back({coarsest, {x, y, z}});
    order(coarsest, roots);
    for (const BrickKey& r : roots) {
      if (!is_resident(r)) {
        if (!outside(tree.brick_box(r)) && tree.may_contribute(r, params))
          plan.missing.push_back(r);
        continue;
      }
      visit(r);
    }
    std::reverse(plan.missing.begin(), plan.missing.end());  // nearest first
    std::stable_sort(plan.missing.begin(), plan.missing.end(),
                     [](const BrickKey& a, const BrickKey& b) { return a.level > b.level; });
    plan.lod_pixels = lod;
  }
};

bool finite_matrix(const Mat4& m) {
  for (const auto& col : m.m)
    for (double v : col)
      if (!std::isfinite(v)) return false;
  return true;
}

}  // namespace

BrickPlan plan_bricks(const BrickTree& tree, const Camera& cam, const RenderParams& params,
                      const PlanOptions& options, unsigned channels, const ResidentFn& resident) {
  const int levels = tree.levels();
  // An incomplete tree (TreeBuild::kCoarseFirst) has ranged its coarsest level only.
  const int coarsest = !tree.complete() || options.coarsest_level < 0
                           ? levels - 1
                           : std::min(options.coarsest_level, levels - 1);
  const int finest = tree.complete() ? std::clamp(options.finest_level, 0, coarsest) : coarsest;
  Mat4 vp = cam.view_projection();
  if (!finite_matrix(vp) || !is_finite(cam.eye) || !is_finite(cam.forward)) return {};
  Vec3 eye_point = cam.eye;
  if (cam.orthographic)
    eye_point = cam.eye - cam.forward * (1e6 * length(tree.volume_box().size()) + 1e6);
  auto make = [&](double lod, const ResidentFn* res) {
    Planner p{tree,   cam,      params,         channels,
              finest, coarsest, options.border, lod,
              res,    vp,       eye_point,      std::tan(cam.fov_y_deg * kPi / 360.0),
              {}};
    p.run();
    return p.plan;
  };
  double lod =
      options.lod_pixels > 0 && std::isfinite(options.lod_pixels) ? options.lod_pixels : 1.0;
  BrickPlan ideal = make(lod, nullptr);
  // Coarsen for the budget until the bricks fit or every one is of the coarsest level.
  auto all_coarsest = [&](const BrickPlan& p) {
    for (const BrickKey& k : p.draw)
      if (k.level < coarsest) return false;
    return true;
  };
  for (int i = 0;
       options.max_bytes > 0 && ideal.bytes > options.max_bytes && !all_coarsest(ideal) && i < 64;
       ++i) {
    lod *= 2;
    ideal = make(lod, nullptr);
  }
  if (!resident) return ideal;
  return make(lod, &resident);
}

}  // namespace vispack::render

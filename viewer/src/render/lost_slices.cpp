#include "vispack/render/lost_slices.h"

#include <algorithm>
#include <cstring>
#include <stdexcept>

namespace vispack::render {

std::vector<std::int64_t> lost_slices_at_level(const std::vector<std::int64_t>& lost0, int level,
                                               std::int64_t nz_level) {
  std::vector<std::int64_t> out;
  for (std::int64_t z : lost0) {
    std::int64_t zl = z >> level;
    if (z >= 0 && zl < nz_level) out.push_back(zl);
  }
  std::sort(out.begin(), out.end());
  out.erase(std::unique(out.begin(), out.end()), out.end());
  return out;
}

LostSliceSource::LostSliceSource(std::shared_ptr<const VolumeSource> inner,
                                 std::vector<std::int64_t> lost0)
    : inner_(std::move(inner)) {
  if (!inner_) throw std::invalid_argument("LostSliceSource: null source");
  const std::int64_t nz0 = inner_->level(0).dims[2];
  std::vector<std::int64_t> valid;
  for (std::int64_t z : lost0)
    if (z >= 0 && z < nz0) valid.push_back(z);
  for (int l = 0; l < inner_->level_count(); ++l)
    lost_.push_back(lost_slices_at_level(valid, l, inner_->level(l).dims[2]));
}

bool LostSliceSource::is_lost(int level, std::int64_t z) const {
  const std::vector<std::int64_t>& v = lost_[std::size_t(level)];
  return std::binary_search(v.begin(), v.end(), z);
}

void LostSliceSource::read_region(Channel c, int level, const Region& r, void* out) const {
  inner_->read_region(c, level, r, out);
  if (c != Channel::kRgba || level < 0 || level >= int(lost_.size())) return;
  const std::vector<std::int64_t>& lost = lost_[std::size_t(level)];
  if (lost.empty() || r.voxels() == 0) return;
  const std::int64_t nz = inner_->level(level).dims[2];
  const std::size_t plane = std::size_t(r.size[0] * r.size[1]);
  auto* data = static_cast<std::uint8_t*>(out);
  // One slice of the region's footprint: from `out` when it is inside the region (valid slices
  // there are never modified), else read from the wrapped source.
  Region one = r;
  one.size[2] = 1;
  auto slice = [&](std::int64_t z, std::vector<std::uint8_t>& tmp) -> const std::uint8_t* {
    if (z >= r.offset[2] && z < r.offset[2] + r.size[2])
      return data + 4 * plane * std::size_t(z - r.offset[2]);
    tmp.resize(4 * plane);
    one.offset[2] = z;
    inner_->read_region(Channel::kRgba, level, one, tmp.data());
    return tmp.data();
  };
  std::vector<std::uint8_t> below_tmp, above_tmp;
  for (std::int64_t z = r.offset[2]; z < r.offset[2] + r.size[2]; ++z) {
    if (!std::binary_search(lost.begin(), lost.end(), z)) continue;
    std::int64_t a = z - 1, b = z + 1;
    while (a >= 0 && is_lost(level, a))
      --a;
    while (b < nz && is_lost(level, b))
      ++b;
    std::uint8_t* dst = data + 4 * plane * std::size_t(z - r.offset[2]);
    if (a < 0 && b >= nz) continue;  // nothing valid to sample from
    if (a < 0 || b >= nz) {
      std::memcpy(dst, slice(a < 0 ? b : a, below_tmp), 4 * plane);
      continue;
    }
    const std::uint8_t* pa = slice(a, below_tmp);
    const std::uint8_t* pb = slice(b, above_tmp);
    const double w = double(z - a) / double(b - a);
    for (std::size_t i = 0; i < plane; ++i) {
      const double aa = pa[4 * i + 3], ab = pb[4 * i + 3];
      const double alpha = (1 - w) * aa + w * ab;
      for (int k = 0; k < 3; ++k) {
        double v = alpha > 0 ? ((1 - w) * aa * pa[4 * i + k] + w * ab * pb[4 * i + k]) / alpha
                             : (1 - w) * pa[4 * i + k] + w * pb[4 * i + k];
        dst[4 * i + k] = std::uint8_t(std::clamp(v + 0.5, 0.0, 255.0));
      }
      dst[4 * i + 3] = std::uint8_t(std::clamp(alpha + 0.5, 0.0, 255.0));
    }
  }
}

BrickStats LostSliceSource::brick_stats(Channel c, int level,
                                        const std::array<std::int64_t, 3>& brick) const {
  if (c == Channel::kRgba && level >= 0 && level < int(lost_.size())) {
    Region r = brick_region(*this, level, brick);
    const std::vector<std::int64_t>& lost = lost_[std::size_t(level)];
    auto it = std::lower_bound(lost.begin(), lost.end(), r.offset[2]);
    if (it != lost.end() && *it < r.offset[2] + r.size[2]) {  // computed from the filled data
      std::lock_guard<std::mutex> lock(scratch_mutex_);
      scratch_.resize(std::size_t(r.voxels()) * std::size_t(channel_bytes(c)));
      read_region(c, level, r, scratch_.data());
      return compute_brick_stats(c, scratch_.data(), std::size_t(r.voxels()));
    }
  }
  return inner_->brick_stats(c, level, brick);
}

std::shared_ptr<const VolumeSource> fill_lost_slices(std::shared_ptr<const VolumeSource> source) {
  if (!source) return source;
  std::vector<std::int64_t> lost = source->lost_slices();
  if (lost.empty()) return source;
  return std::make_shared<LostSliceSource>(std::move(source), std::move(lost));
}

}  // namespace vispack::render

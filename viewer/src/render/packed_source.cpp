// VolumeSource over the memory-mapped format reader (vispack::format::Reader).
#include <algorithm>
#include <cstring>
#include <stdexcept>

#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/format/reader.h"
#include "vispack/render/volume.h"

namespace vispack::render {
namespace {

class PackedSource final : public VolumeSource {
 public:
  explicit PackedSource(const std::string& path) : reader_(format::Reader::open(path)) {
    for (Channel c : {Channel::kRgba, Channel::kCt, Channel::kLabels}) {
      std::optional<int> idx = reader_.find_channel(channel_name(c));
      if (!idx) continue;
      format::ChannelType t = reader_.channels()[std::size_t(*idx)].type;
      bool ok = c == Channel::kRgba ? t == format::ChannelType::kRgba8
                                    : (c == Channel::kCt ? t == format::ChannelType::kInt16
                                                         : format::is_label_type(t));
      if (!ok)
        throw FormatError(cat(path, ": channel '", channel_name(c), "' has unexpected type ",
                              format::channel_type_name(t)));
      index_[int(c)] = *idx;
      type_[int(c)] = t;
    }
  }
  std::string name() const override { return reader_.path(); }
  int level_count() const override { return reader_.level_count(); }
  LevelGeometry level(int level) const override {
    const format::LevelInfo& l = reader_.level(level);
    LevelGeometry g;
    g.dims = l.dims;
    g.spacing_mm = {l.spacing_mm[0], l.spacing_mm[1], l.spacing_mm[2]};
    g.origin_mm = {l.origin_mm[0], l.origin_mm[1], l.origin_mm[2]};
    return g;
  }
  bool has_channel(Channel c) const override { return index_[int(c)] >= 0; }
  std::vector<Label> labels() const override {
    std::vector<Label> out;
    for (const format::LabelEntry& e : reader_.label_table())
      out.push_back({e.id, e.name, e.colour});
    return out;
  }
  int brick_edge() const override { return reader_.brick_edge(); }
  BrickStats brick_stats(Channel c, int level,
                         const std::array<std::int64_t, 3>& b) const override {
    int idx = index_[int(c)];
    if (idx < 0) throw std::out_of_range(cat(reader_.path(), ": no channel ", channel_name(c)));
    const format::BrickInfo& info = reader_.brick(idx, level, b[0], b[1], b[2]);
    BrickStats s;
    s.min = info.min;
    s.max = info.max;
    if (c == Channel::kLabels) s.labels = reader_.brick_labels(info);
    return s;
  }
  std::vector<std::int64_t> lost_slices() const override {
    std::vector<std::int64_t> out;
    const nlohmann::json& m = reader_.metadata();
    auto extra = m.find("extra");
    if (extra == m.end() || !extra->is_object()) return out;
    auto slices = extra->find("slices");
    if (slices == extra->end() || !slices->is_object()) return out;
    auto black = slices->find("black");
    if (black == slices->end() || !black->is_array()) return out;
    const std::int64_t nz = reader_.dims(0)[2];
    for (const nlohmann::json& k : *black)  // ignore anything that is not a slice of the volume
      if (k.is_number_integer() && k.get<std::int64_t>() >= 0 && k.get<std::int64_t>() < nz)
        out.push_back(k.get<std::int64_t>());
    std::sort(out.begin(), out.end());
    out.erase(std::unique(out.begin(), out.end()), out.end());
    return out;
  }
  void read_region(Channel c, int level, const Region& r, void* out) const override {
    int idx = index_[int(c)];
    if (idx < 0) throw std::out_of_range(cat(reader_.path(), ": no channel ", channel_name(c)));
    verify_bricks(idx, level, r);
    if (c == Channel::kLabels && type_[int(c)] == format::ChannelType::kUint8) {
      // Widen uint8 labels in place, back to front (the uint8 data fills the first half).
      reader_.read_region(idx, level, r.offset[0], r.offset[1], r.offset[2], r.size[0], r.size[1],
                          r.size[2], out);
      auto* bytes = static_cast<std::uint8_t*>(out);
      auto* wide = static_cast<std::uint16_t*>(out);
      for (std::int64_t i = r.voxels(); i-- > 0;)
        wide[i] = bytes[i];
      return;
    }
    reader_.read_region(idx, level, r.offset[0], r.offset[1], r.offset[2], r.size[0], r.size[1],
                        r.size[2], out);
  }

 private:
  // Checks the xxHash64 of every stored brick payload the region touches (docs/RELIABILITY.md: a
  // brick that fails its checksum is reported, never shown as garbage). Throws FormatError naming
  // the file, channel, level and brick. Cheap next to decoding (xxHash64 runs at memory speed).
  void verify_bricks(int idx, int level, const Region& r) const {
    const std::int64_t e = reader_.brick_edge();
    for (std::int64_t bz = r.offset[2] / e; bz * e < r.offset[2] + r.size[2]; ++bz)
      for (std::int64_t by = r.offset[1] / e; by * e < r.offset[1] + r.size[1]; ++by)
        for (std::int64_t bx = r.offset[0] / e; bx * e < r.offset[0] + r.size[0]; ++bx) {
          const format::BrickInfo& b = reader_.brick(idx, level, bx, by, bz);
          if (b.stored_size == 0) continue;  // uniform brick: nothing stored
          const format::ByteView p = reader_.payload(b);
          if (xxh64(p.data, p.size) != b.checksum)
            throw FormatError(cat(reader_.path(), ": brick (", bx, ", ", by, ", ", bz,
                                  ") of channel '", reader_.channels()[std::size_t(idx)].name,
                                  "' level ", level, ": checksum mismatch"));
        }
  }

  format::Reader reader_;
  int index_[kChannelCount] = {-1, -1, -1};
  format::ChannelType type_[kChannelCount] = {};
};

}  // namespace

std::unique_ptr<VolumeSource> open_packed(const std::string& path) {
  return std::make_unique<PackedSource>(path);
}

}  // namespace vispack::render

// Shared helpers of the format tests: deterministic synthetic volumes resembling the data
// (smooth CT with noise, a body in blue gel, piecewise-constant labels), a naive reference
// pyramid, temporary files and file-byte surgery.
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/hash.h"
#include "vispack/format/format.h"

namespace vispack::format::testing {

using Dims = std::array<std::int64_t, 3>;

// This process's scratch folder (a vispack_test_support TempDir), removed when the process ends
// unless VISPACK_KEEP_TEST_DIRS is set.
inline std::filesystem::path temp_dir() {
  static const vispack::test::TempDir dir("vispack-format");
  return dir.path();
}

inline std::string temp_path(const std::string& name) {
  static std::atomic<int> counter{0};
  std::filesystem::path dir = temp_dir();
  std::filesystem::create_directories(dir);
  return (dir / (std::to_string(counter++) + "_" + name)).string();
}

inline std::vector<std::uint8_t> read_bytes(const std::string& path) {
  std::string s = vispack::read_file(path);
  return std::vector<std::uint8_t>(s.begin(), s.end());
}
inline void write_bytes(const std::string& path, const std::vector<std::uint8_t>& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(bytes.data()), std::streamsize(bytes.size()));
}

// A volume in memory: one buffer per channel. Label channels hold uint16 (as passed to the
// writer); `stored` buffers hold what the file holds (labels narrowed when stored as uint8).
struct Volume {
  Dims dims{};
  std::vector<ChannelSpec> channels;
  std::vector<std::vector<std::uint8_t>> data;
  std::vector<LabelEntry> label_table;
};

// rgba: a body (ellipsoid) of tissue colours, alpha 255 inside, blue gel with alpha 0 outside;
// ct: smooth HU field with noise, -1000 (air) outside; labels: piecewise-constant IDs
// (slabs of organs), 0 outside. `max_label` > 255 forces a uint16 label channel.
inline Volume make_volume(Dims d, std::uint32_t seed = 1, std::uint32_t max_label = 40) {
  Volume v;
  v.dims = d;
  v.channels = {
      {"rgba", ChannelType::kRgba8}, {"ct", ChannelType::kInt16}, {"labels", ChannelType::kUint16}};
  const std::size_t n = std::size_t(d[0] * d[1] * d[2]);
  v.data.resize(3);
  v.data[0].resize(n * 4);
  v.data[1].resize(n * 2);
  v.data[2].resize(n * 2);
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> noise(-20, 20);
  for (std::uint32_t id = 1; id <= max_label; id = id < 30 ? id + 1 : id * 3) {
    v.label_table.push_back({id,
                             "structure_" + std::to_string(id),
                             {std::uint8_t(id * 37), std::uint8_t(id * 11), 80}});
  }
  const double cx = (d[0] - 1) / 2.0, cy = (d[1] - 1) / 2.0, cz = (d[2] - 1) / 2.0;
  for (std::int64_t z = 0; z < d[2]; ++z) {
    for (std::int64_t y = 0; y < d[1]; ++y) {
      for (std::int64_t x = 0; x < d[0]; ++x) {
        const std::size_t i = std::size_t((z * d[1] + y) * d[0] + x);
        double rx = (x - cx) / (0.4 * d[0] + 0.5), ry = (y - cy) / (0.4 * d[1] + 0.5),
               rz = (z - cz) / (0.45 * d[2] + 0.5);
        bool inside = rx * rx + ry * ry + rz * rz < 1.0;
        std::uint8_t* p = &v.data[0][4 * i];
        std::int16_t hu;
        std::uint16_t label = 0;
        if (inside) {
          p[0] = std::uint8_t(150 + 60 * std::sin(0.2 * x) + noise(rng) / 4);
          p[1] = std::uint8_t(90 + 30 * std::cos(0.13 * y) + noise(rng) / 4);
          p[2] = std::uint8_t(70 + noise(rng));
          p[3] = 255;
          hu = std::int16_t(40 + 300 * std::sin(0.05 * (x + y)) * std::cos(0.07 * z) + noise(rng));
          const auto& table = v.label_table;
          label = std::uint16_t(table[std::size_t((x / 5 + y / 7 + z / 3) % table.size())].id);
        } else {
          p[0] = 20;
          p[1] = 40;
          p[2] = 160;
          p[3] = 0;
          hu = -1000;
        }
        std::memcpy(&v.data[1][2 * i], &hu, 2);
        std::memcpy(&v.data[2][2 * i], &label, 2);
      }
    }
  }
  return v;
}

inline WriterOptions options_for(const Volume& v, int edge, int threads = 2) {
  WriterOptions o;
  o.dims = v.dims;
  o.spacing_mm = {0.33, 0.5, 1.0};
  o.origin_mm = {-10.0, 5.0, 2.5};
  o.brick_edge = edge;
  o.threads = threads;
  o.channels = v.channels;
  o.label_table = v.label_table;
  o.extra_metadata = {{"provenance", {{"tool", "format tests"}}}};
  return o;
}

// Appends a slab's level-1 slices to a Writer fed as a merge feeds it: `level1` as
// encode_level0_slab gives them (per stored channel, `n1` slices one after the other).
inline void append_level1_slices(Writer& w, const std::vector<std::vector<std::uint8_t>>& level1,
                                 std::size_t n1) {
  for (std::size_t k = 0; k < n1; ++k) {
    std::vector<const void*> slice;
    for (const auto& l : level1)
      slice.push_back(l.data() + l.size() / n1 * k);
    w.append_level1_slice(slice);
  }
}

inline void write(const std::string& path, const Volume& v, const WriterOptions& o) {
  std::vector<const void*> ptrs;
  for (const auto& d : v.data)
    ptrs.push_back(d.data());
  write_volume(path, o, ptrs);
}

// The file's bytes for a channel stored as `type` from the writer's input (labels as uint16).
inline std::vector<std::uint8_t> to_stored(const std::vector<std::uint8_t>& input,
                                           ChannelType input_type, ChannelType stored) {
  if (!(is_label_type(input_type) && stored == ChannelType::kUint8)) return input;
  std::vector<std::uint8_t> out(input.size() / 2);
  for (std::size_t i = 0; i < out.size(); ++i)
    out[i] = input[2 * i];  // little-endian low byte
  return out;
}

// Naive reference reduction of a whole level (all children gathered in z, y, x order).
inline std::vector<std::uint8_t> reference_downsample(const std::vector<std::uint8_t>& src, Dims d,
                                                      ChannelType type, Dims* out_dims) {
  Dims o{(d[0] + 1) / 2, (d[1] + 1) / 2, (d[2] + 1) / 2};
  *out_dims = o;
  const std::size_t vb = channel_type_bytes(type);
  std::vector<std::uint8_t> out(std::size_t(o[0] * o[1] * o[2]) * vb);
  for (std::int64_t z = 0; z < o[2]; ++z)
    for (std::int64_t y = 0; y < o[1]; ++y)
      for (std::int64_t x = 0; x < o[0]; ++x) {
        std::uint8_t ch[32];
        int n = 0;
        for (std::int64_t zz = 2 * z; zz < std::min(d[2], 2 * z + 2); ++zz)
          for (std::int64_t yy = 2 * y; yy < std::min(d[1], 2 * y + 2); ++yy)
            for (std::int64_t xx = 2 * x; xx < std::min(d[0], 2 * x + 2); ++xx, ++n)
              std::memcpy(ch + n * vb, &src[std::size_t((zz * d[1] + yy) * d[0] + xx) * vb], vb);
        std::uint8_t* dst = &out[std::size_t((z * o[1] + y) * o[0] + x) * vb];
        if (type == ChannelType::kRgba8) {
          auto r = reduce_rgba_alpha_weighted(ch, n);
          std::memcpy(dst, r.data(), 4);
        } else if (type == ChannelType::kInt16) {
          std::int16_t c[8];
          std::memcpy(c, ch, 2 * n);
          std::int16_t r = reduce_mean_i16(c, n);
          std::memcpy(dst, &r, 2);
        } else if (type == ChannelType::kUint8) {
          std::uint16_t c[8];
          for (int i = 0; i < n; ++i)
            c[i] = ch[i];
          *dst = std::uint8_t(reduce_majority(c, n));
        } else {
          std::uint16_t c[8];
          std::memcpy(c, ch, 2 * n);
          std::uint16_t r = reduce_majority(c, n);
          std::memcpy(dst, &r, 2);
        }
      }
  return out;
}

// ---- File-byte surgery (little-endian fields at the offsets of SPEC.md) ----

inline std::uint64_t get_u64(const std::vector<std::uint8_t>& b, std::size_t off) {
  std::uint64_t v;
  std::memcpy(&v, &b[off], 8);
  return v;
}
inline void set_u64(std::vector<std::uint8_t>& b, std::size_t off, std::uint64_t v) {
  std::memcpy(&b[off], &v, 8);
}
inline void set_u32(std::vector<std::uint8_t>& b, std::size_t off, std::uint32_t v) {
  std::memcpy(&b[off], &v, 4);
}

// A file cut into its parts, to be edited and reassembled with consistent offsets and checksum,
// so that a test reaches the validation behind the checksum.
struct Parts {
  std::vector<std::uint8_t> header, payload, index, labels;
  std::string meta;
};

inline Parts split(const std::vector<std::uint8_t>& f) {
  Parts p;
  p.header.assign(f.begin(), f.begin() + 128);
  const std::uint64_t pend = get_u64(f, 32), moff = get_u64(f, 40), msize = get_u64(f, 48);
  const std::uint64_t ioff = get_u64(f, 56), icount = get_u64(f, 64), loff = get_u64(f, 72);
  p.payload.assign(f.begin() + 4096, f.begin() + std::ptrdiff_t(pend));
  p.meta.assign(f.begin() + std::ptrdiff_t(moff), f.begin() + std::ptrdiff_t(moff + msize));
  p.index.assign(f.begin() + std::ptrdiff_t(ioff), f.begin() + std::ptrdiff_t(ioff + 64 * icount));
  p.labels.assign(f.begin() + std::ptrdiff_t(loff), f.end());
  return p;
}

inline void rechecksum(std::vector<std::uint8_t>& f) {
  std::uint64_t moff = std::min<std::uint64_t>(get_u64(f, 40), f.size());
  std::vector<std::uint8_t> covered(f.begin(), f.begin() + 120);
  covered.insert(covered.end(), f.begin() + std::ptrdiff_t(moff), f.end());
  set_u64(f, 120, vispack::xxh64(covered.data(), covered.size()));
}

inline std::vector<std::uint8_t> assemble(
    const Parts& p, const std::function<void(std::vector<std::uint8_t>&)>& patch = {}) {
  std::vector<std::uint8_t> f = p.header;
  f.resize(4096, 0);
  f.insert(f.end(), p.payload.begin(), p.payload.end());
  const std::uint64_t pend = f.size();
  f.insert(f.end(), p.meta.begin(), p.meta.end());
  f.resize((f.size() + 7) / 8 * 8, 0);
  const std::uint64_t ioff = f.size();
  f.insert(f.end(), p.index.begin(), p.index.end());
  const std::uint64_t loff = f.size();
  f.insert(f.end(), p.labels.begin(), p.labels.end());
  set_u64(f, 16, f.size());
  set_u64(f, 32, pend);
  set_u64(f, 40, pend);
  set_u64(f, 48, p.meta.size());
  set_u64(f, 56, ioff);
  set_u64(f, 64, p.index.size() / 64);
  set_u64(f, 72, loff);
  set_u64(f, 80, p.labels.size() / 4);
  if (patch) patch(f);
  rechecksum(f);
  return f;
}

}  // namespace vispack::format::testing

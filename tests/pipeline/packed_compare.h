// Test helper: the packed volume of a colour stack with files missing against the packed volume
// of the complete stack, output slice by output slice at the same z (docs/ARCHITECTURE.md "Each
// input at its own z": output z is the colour slot, a missing file an empty slice at its z).
// Reads level 0 whole: small test volumes only. Header-only, for the pipeline tests.
#pragma once

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include "vispack/format/reader.h"

namespace vispack::test {

// Level 0 of a packed file: colour with alpha, CT in HU (empty without a ct channel), labels
// widened to uint16 (empty without labels).
struct PackedLevel0 {
  std::array<std::int64_t, 3> dims{};
  std::vector<std::uint8_t> rgba;
  std::vector<std::int16_t> ct;
  std::vector<std::uint16_t> labels;
  std::size_t plane() const { return std::size_t(dims[0]) * std::size_t(dims[1]); }
};

inline PackedLevel0 read_packed_level0(const std::string& path) {
  const format::Reader reader = format::Reader::open(path);
  PackedLevel0 v;
  v.dims = reader.dims();
  v.rgba = reader.read_level("rgba", 0);
  if (reader.find_channel("ct")) {
    const std::vector<std::uint8_t> bytes = reader.read_level("ct", 0);
    v.ct.resize(bytes.size() / 2);
    std::memcpy(v.ct.data(), bytes.data(), bytes.size());
  }
  if (const auto c = reader.find_channel("labels")) {
    const std::vector<std::uint8_t> bytes = reader.read_level(*c, 0);
    if (reader.channels()[std::size_t(*c)].type == format::ChannelType::kUint8) {
      v.labels.assign(bytes.begin(), bytes.end());
    } else {
      v.labels.resize(bytes.size() / 2);
      std::memcpy(v.labels.data(), bytes.data(), bytes.size());
    }
  }
  return v;
}

// Output slice z is an empty slot's slice: colour and alpha 0, labels 0, CT −1024 HU.
inline bool packed_slice_is_empty(const PackedLevel0& v, std::int64_t z) {
  const std::size_t p = v.plane(), o = p * std::size_t(z);
  const auto rgba = v.rgba.begin() + std::ptrdiff_t(o * 4);
  if (std::any_of(rgba, rgba + std::ptrdiff_t(p * 4), [](std::uint8_t b) { return b != 0; }))
    return false;
  for (std::size_t i = 0; i < p; ++i) {
    if (!v.ct.empty() && v.ct[o + i] != -1024) return false;
    if (!v.labels.empty() && v.labels[o + i] != 0) return false;
  }
  return true;
}

// How far slice `za` of `a` agrees with slice `zb` of `b`: the IoU of the bodies (alpha ≥ 128),
// and over the voxels in both bodies the fraction whose CT is the same to 1 HU and whose labels
// are equal (1 without the channel).
struct PackedSliceAgreement {
  double body_iou = 0, ct_equal = 1, labels_equal = 1;
};
inline PackedSliceAgreement packed_slice_agreement(const PackedLevel0& a, std::int64_t za,
                                                   const PackedLevel0& b, std::int64_t zb) {
  const std::size_t p = a.plane(), oa = p * std::size_t(za), ob = p * std::size_t(zb);
  std::size_t both = 0, either = 0, ct_same = 0, labels_same = 0;
  for (std::size_t i = 0; i < p; ++i) {
    const bool in_a = a.rgba[(oa + i) * 4 + 3] >= 128, in_b = b.rgba[(ob + i) * 4 + 3] >= 128;
    either += in_a || in_b;
    if (!(in_a && in_b)) continue;
    ++both;
    if (!a.ct.empty() && std::abs(int(a.ct[oa + i]) - int(b.ct[ob + i])) <= 1) ++ct_same;
    if (!a.labels.empty() && a.labels[oa + i] == b.labels[ob + i]) ++labels_same;
  }
  PackedSliceAgreement r;
  r.body_iou = either ? double(both) / double(either) : 1.0;
  if (both && !a.ct.empty()) r.ct_equal = double(ct_same) / double(both);
  if (both && !a.labels.empty()) r.labels_equal = double(labels_same) / double(both);
  return r;
}

// The volume of the stack with files missing (`gap`) has the complete stack's depth; each slice in
// `missing_z` is empty; every other slice agrees with the complete stack's slice at the same z to
// `min_iou` (bodies), `min_ct` and `min_labels` (fractions of the common body). Returns the
// smallest agreement seen (for the test's printout).
inline PackedSliceAgreement expect_gaps_at_their_z(const PackedLevel0& gap,
                                                   const PackedLevel0& whole,
                                                   const std::vector<int>& missing_z,
                                                   double min_iou, double min_ct,
                                                   double min_labels) {
  PackedSliceAgreement worst{1, 1, 1};
  EXPECT_EQ(gap.dims, whole.dims) << "the volume with missing colour files is not as deep";
  if (gap.dims != whole.dims) return worst;
  for (std::int64_t z = 0; z < gap.dims[2]; ++z) {
    if (std::find(missing_z.begin(), missing_z.end(), int(z)) != missing_z.end()) {
      EXPECT_TRUE(packed_slice_is_empty(gap, z)) << "output slice " << z << " (missing) not empty";
      continue;
    }
    const PackedSliceAgreement s = packed_slice_agreement(gap, z, whole, z);
    worst.body_iou = std::min(worst.body_iou, s.body_iou);
    worst.ct_equal = std::min(worst.ct_equal, s.ct_equal);
    worst.labels_equal = std::min(worst.labels_equal, s.labels_equal);
    EXPECT_GE(s.body_iou, min_iou) << "output slice " << z;
    EXPECT_GE(s.ct_equal, min_ct) << "output slice " << z;
    EXPECT_GE(s.labels_equal, min_labels) << "output slice " << z;
  }
  std::printf(
      "packed against the complete stack, worst slice: body IoU %.4f, CT equal %.4f, "
      "labels equal %.4f\n",
      worst.body_iou, worst.ct_equal, worst.labels_equal);
  return worst;
}

}  // namespace vispack::test

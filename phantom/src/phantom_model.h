// Internal: the analytic phantom model behind make_phantom (phantom.h). Not installed.
//
// Coordinates: (x, y) are continuous pixel coordinates of the output (RGB truth) grid, pixel
// centres at integers; slice k is the slice index. The model works in normalised units
// X = (x − cx) / (H/2), Y = (y − cy) / (H/2), so the body has the same shape in every preset, and
// uses a texture defined in output pixels and slices (smooth 3-D value noise fixed in the volume).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <random>
#include <string>
#include <vector>

namespace vispack::phantom::detail {

// splitmix64 finaliser: the one hash behind every random number of the phantom.
inline std::uint64_t mix64(std::uint64_t z) {
  z += 0x9e3779b97f4a7c15ull;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

// Portable random numbers: std::mt19937_64 is specified bit for bit, std:: distributions are not,
// so the distributions are ours.
class Random {
 public:
  explicit Random(std::uint64_t seed);
  double uniform();                      // [0, 1)
  double uniform(double lo, double hi);  // [lo, hi)
  double normal(double sigma = 1.0);     // Box-Muller, mean 0
  // Four standard normal samples from one 64-bit draw, through a table of normal quantiles
  // (16-bit resolution: plenty for sensor noise, and no transcendental calls per sample).
  void normal4(const class GaussianTable& table, float out[4]);
  std::uint64_t next();

 private:
  std::mt19937_64 engine_;
  double spare_ = 0.0;
  bool has_spare_ = false;
};

// Φ⁻¹((i + 0.5) / 65536) for i = 0..65535: exact normal quantiles, computed once.
class GaussianTable {
 public:
  GaussianTable();
  float operator[](std::size_t i) const { return values_[i]; }

 private:
  std::vector<float> values_;
};

// Labels of the phantom (0 = background/gel).
enum Label : std::uint16_t {
  kBackground = 0,
  kSkin = 1,
  kFat = 2,
  kMuscle = 3,
  kBone = 4,
  kLungs = 5,
  kHeart = 6,
  kLiver = 7,
  kKidneys = 8,
  kConnective = 9,
  kLabelCount = 10
};
struct LabelInfo {
  const char* name;
  std::array<int, 3> palette;  // segmentation colour (far apart: > 80 in RGB distance)
};
const LabelInfo& label_info(int label);

// One octave of value noise at a fixed slice: a cached 2-D lattice (the z interpolation done once).
class NoiseLayer {
 public:
  NoiseLayer() = default;
  // `scale_px` / `scale_slices`: lattice spacing; the cache covers x in [x_lo, x_hi], y likewise.
  NoiseLayer(std::uint64_t key, double scale_px, double scale_slices, double slice, double x_lo,
             double x_hi, double y_lo, double y_hi);
  float at(double x, double y) const;  // in [-1, 1], smooth

 private:
  float lattice(std::int64_t ix, std::int64_t iy) const;
  float compute(std::int64_t ix, std::int64_t iy) const;
  std::uint64_t key_ = 0;
  double inv_scale_ = 1.0;
  std::int64_t iz_ = 0;
  float fz_ = 0.f;
  std::int64_t x0_ = 0, y0_ = 0, nx_ = 0, ny_ = 0;
  std::vector<float> cache_;
};

// How the anatomy varies along the stack (the presets' knobs; the defaults are the classic
// tiny/small/medium/vhp body).
struct Anatomy {
  bool fiducials = true;  // the two green fiducial tubes, fixed in the frame, in every slice
  bool varying = false;   // t = k / (N − 1) whatever N; organs move; taper; fresh texture
  double body_scale = 1;  // body size relative to the classic body
  double shift_x = 0, shift_y = 0;  // body centre moves steadily by this over the stack
                                    // (normalised units, from −shift/2 to +shift/2)
  bool taper = false;  // body size ∝ sin(π t)^0.3: nothing at both ends of the stack
  // A whole body from head to toes (the `male` presets; t = k / (N − 1)): the head tapering
  // from nothing, the torso with an arm beside it on each side from the shoulders to the hands
  // (gaps from 2 to 40 output px at 1216 px frame height, scaled with the frame, at least 2 px;
  // the right arm rests on the table in part of the stack), the pelvis parting into two legs,
  // two feet, then five toes per foot tapering to nothing. The CT shows a table (a bar
  // `table_px` output px thick, under the body, touching the torso and the right arm in some
  // slices) instead of the classic holder ring.
  bool limbs = false;
  double table_px = 0;  // table thickness, output pixels (limbs only)
};

// One limb cross-section of a slice (an arm, a hand, a leg, a foot, a toe): an ellipse in body
// coordinates (normalised units), skin, fat, muscle and (bone > 0) a bone of `bone` × the smaller
// semi-axis at its centre.
struct Limb {
  double x = 0, y = 0, a = 0, b = 0, bone = 0;
};
inline constexpr int kMaxLimbs = 12;

// Per-slice parameters of the model (shapes and texture at slice k).
struct SliceParams {
  int slice = 0;
  double t = 0;           // slice / (slices − 1), 0..1
  double a = 0, b = 0;    // body semi-axes (normalised units)
  double x0 = 0, y0 = 0;  // body centre (normalised units, 0 = frame centre)
  std::array<std::array<double, 2>, 6> organ_shift{};  // organ centre offsets (body-relative)
  std::array<double, 4> lobes{};  // cos/sin of the 3-fold and 2-fold lobe phases
  double fat_x = 0, fat_y = 0;    // fat thickness
  double lung = 0, heart = 0, liver = 0, kidney = 0, rib = 0, notch = 0;  // sizes 0..1
  std::array<std::array<double, 2>, 6> ribs{};  // rib centres (body-relative units)
  std::array<Limb, kMaxLimbs> limbs{};          // Anatomy::limbs: the parts besides the torso
  int limb_count = 0;
  double table_top = 0;               // Anatomy::limbs: the table's top edge (frame units, y down)
  std::array<NoiseLayer, 4> texture;  // octaves of the tissue texture
  NoiseLayer marbling;                // slow second field (fat marbling, hue)
};

// What the model gives at one point.
// A model colour value as an 8-bit level: rounded, clamped to 0..255.
inline std::uint8_t to_u8(double v) {
  return static_cast<std::uint8_t>(std::clamp(std::lround(v), 0L, 255L));
}

struct Sample {
  std::uint16_t label = 0;
  bool body = false;  // inside the body mask (label > 0)
  float rgb[3] = {0, 0, 0};
  float hu = -1000.f;
};

class Model {
 public:
  Model(int width, int height, int slices, std::uint64_t seed, const Anatomy& anatomy = {});
  SliceParams slice(int k) const;
  // Evaluates the model at output-grid pixel (x, y) of slice s. `edge_px` is the width (output
  // pixels) over which colours/HU blend across a boundary (labels and mask are hard).
  void eval(const SliceParams& s, double x, double y, double edge_px, bool want_rgb, bool want_ct,
            Sample& out) const;

  // Largest extent of the body from the frame centre (normalised units), for frame-margin
  // checks and the CT holder.
  static constexpr double kBodyA = 0.85, kBodyB = 0.58;
  static double body_max_a(const Anatomy& anatomy = {});
  static double body_max_b(const Anatomy& anatomy = {});

 private:
  int width_, height_, slices_;
  std::uint64_t seed_;
  Anatomy anatomy_;
  double cx_, cy_, half_;
};

}  // namespace vispack::phantom::detail

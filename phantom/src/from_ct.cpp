// make_phantom_from_ct: colour, seg and truth synthesised from a real CT (from_ct.h).
#include "vispack/phantom/from_ct.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <numeric>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "phantom_model.h"
#include "truth_json.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/common/nrrd.h"
#include "vispack/common/parallel.h"
#include "vispack/common/progress.h"
#include "vispack/pipeline/core/config.h"
#include "vispack/pipeline/core/slice_list.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vispack::phantom {
namespace {

namespace fs = std::filesystem;
using detail::GaussianTable;
using detail::mix64;
using detail::NoiseLayer;
using detail::Random;
using ojson = nlohmann::ordered_json;

constexpr double kNoiseSigma = 3.0;   // colour sensor noise, 8-bit levels
constexpr double kGainRange = 0.06;   // brightness gain 1 ± 6 %
constexpr double kTiltRange = 0.05;   // lighting gradient up to ±5 % across the frame
constexpr double kDriftPx = 0.3;      // random-walk step σ, pixels
constexpr double kDriftDeg = 0.05;    // random-walk step σ, degrees
constexpr double kSkinMm = 2.0;       // skin: body within this depth
constexpr double kBoneHu = 250.0;     // bone above
constexpr double kFatHu = -30.0;      // fat at or below (inside the body)
constexpr double kFrameMarginPx = 2;  // the body keeps this far from the colour frame's edge

enum CtLabel : std::uint16_t { kGel = 0, kSkin = 1, kFat = 2, kSoft = 3, kBone = 4, kCount = 5 };
struct ClassInfo {
  const char* name;
  std::array<int, 3> palette;
};
const ClassInfo kClasses[kCount] = {
    {"background", {0, 0, 0}},      {"skin", {230, 180, 140}}, {"fat", {255, 240, 80}},
    {"soft tissue", {200, 40, 40}}, {"bone", {245, 245, 245}},
};

// ---- the CT reader ----

CtVolume read_nrrd_ct(const std::string& path) {
  const NrrdVolume v = read_nrrd(path);
  if (v.components != 1) throw InputError(cat(path, ": CT must be scalar, has ", v.components));
  CtVolume ct;
  ct.width = int(v.dims[0]), ct.height = int(v.dims[1]), ct.slices = int(v.dims[2]);
  ct.spacing_mm = v.spacing_mm;
  ct.source = path;
  ct.hu.resize(v.voxel_count());
  auto put = [&](auto* data) {
    for (std::size_t i = 0; i < ct.hu.size(); ++i)
      ct.hu[i] =
          static_cast<std::int16_t>(std::clamp<double>(std::round(double(data[i])), -32768, 32767));
  };
  switch (v.type) {
    case NrrdType::kUint8:
      put(v.as<std::uint8_t>());
      break;
    case NrrdType::kInt8:
      put(v.as<std::int8_t>());
      break;
    case NrrdType::kUint16:
      put(v.as<std::uint16_t>());
      break;
    case NrrdType::kInt16:
      put(v.as<std::int16_t>());
      break;
    case NrrdType::kUint32:
      put(v.as<std::uint32_t>());
      break;
    case NrrdType::kInt32:
      put(v.as<std::int32_t>());
      break;
    case NrrdType::kFloat32:
      put(v.as<float>());
      break;
    case NrrdType::kFloat64:
      put(v.as<double>());
      break;
  }
  return ct;
}

CtVolume read_config_ct(const std::string& config_path) {
  const pipeline::Config config = pipeline::load_config(config_path);
  if (!config.ct) throw InputError(cat(config_path, ": has no ct section"));
  const pipeline::CtSource& src = *config.ct;
  const auto files = pipeline::list_slices(src);
  CtVolume ct;
  ct.source = config_path;
  ct.spacing_mm = {src.pixel_spacing_mm[0], src.pixel_spacing_mm[1], config.spacing_mm[2]};
  ct.slices = int(files.size());
  for (std::size_t k = 0; k < files.size(); ++k) {
    cv::Mat m = pipeline::read_slice(files[k].path, src.raw);
    if (m.channels() != 1) throw InputError(cat(files[k].path, ": CT slice is not grey"));
    if (k == 0) {
      ct.width = m.cols, ct.height = m.rows;
      ct.hu.resize(std::size_t(ct.width) * ct.height * files.size());
    } else if (m.cols != ct.width || m.rows != ct.height) {
      throw InputError(cat(files[k].path, ": ", m.cols, "x", m.rows,
                           " differs from the first CT slice (", ct.width, "x", ct.height, ")"));
    }
    cv::Mat hu;
    m.convertTo(hu, CV_64F, src.slope, src.intercept);
    std::int16_t* out = ct.hu.data() + std::size_t(ct.width) * ct.height * k;
    for (int y = 0; y < ct.height; ++y)
      for (int x = 0; x < ct.width; ++x)
        out[std::size_t(y) * ct.width + x] = static_cast<std::int16_t>(
            std::clamp(std::round(hu.at<double>(y, x)), -32768.0, 32767.0));
  }
  return ct;
}

// ---- the model ----

std::uint8_t to_u8(double v) {
  return static_cast<std::uint8_t>(std::clamp(std::lround(v), 0L, 255L));
}

std::string numbered(const std::string& stem, int number, int digits, const std::string& ext) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%0*d", digits, number);
  return stem + "_" + buffer + ext;
}

double smoothstep(double e0, double e1, double x) {
  const double t = std::clamp((x - e0) / (e1 - e0), 0.0, 1.0);
  return t * t * (3.0 - 2.0 * t);
}

// Union-find over (slice, component) ids, for the 3-D body component.
struct UnionFind {
  std::vector<int> parent;
  int find(int a) {
    while (parent[std::size_t(a)] != a)
      a = parent[std::size_t(a)] = parent[std::size_t(parent[std::size_t(a)])];
    return a;
  }
  void join(int a, int b) {
    a = find(a), b = find(b);
    if (a != b) parent[std::size_t(std::max(a, b))] = std::min(a, b);
  }
};

// What the model needs per output slice: the CT slice, the body mask and the two distance maps.
struct SliceModel {
  cv::Mat ct;       // CV_32F, Wct × Hct, HU
  cv::Mat mask;     // CV_8U 0/1, W × H (the body component B)
  cv::Mat depth;    // CV_32F, distance inside the body to the nearest non-body pixel
  cv::Mat outside;  // CV_32F, distance outside the body to the nearest body pixel
  NoiseLayer tex[3];
  NoiseLayer hue;
};

struct Geometry {
  int W = 0, H = 0, Wct = 0, Hct = 0, scale = 2;
  double cx = 0, cy = 0, cxct = 0, cyct = 0;
  double pixel_mm = 1;
};

float bilinear(const cv::Mat& m, double x, double y) {
  x = std::clamp(x, 0.0, double(m.cols - 1));
  y = std::clamp(y, 0.0, double(m.rows - 1));
  const int x0 = std::min(int(x), m.cols - 2 < 0 ? 0 : m.cols - 2);
  const int y0 = std::min(int(y), m.rows - 2 < 0 ? 0 : m.rows - 2);
  const int x1 = std::min(x0 + 1, m.cols - 1), y1 = std::min(y0 + 1, m.rows - 1);
  const double fx = x - x0, fy = y - y0;
  const float* r0 = m.ptr<float>(y0);
  const float* r1 = m.ptr<float>(y1);
  const double top = r0[x0] + (r0[x1] - r0[x0]) * fx;
  const double bottom = r1[x0] + (r1[x1] - r1[x0]) * fx;
  return static_cast<float>(top + (bottom - top) * fy);
}

// The truth mask counts enclosed in-slice cavities (sinuses, airways surrounded by tissue) as
// body, as a body mask does (the product removes the gel around the body, not air inside it):
// background pixels not 4-connected to the frame's border become body. Written here, apart
// from the pipeline's own hole filling, so that a bug there cannot hide in the truth.
void fill_enclosed_cavities(std::uint8_t* mask01, int W, int H) {
  cv::Mat padded = cv::Mat::zeros(H + 2, W + 2, CV_8UC1);
  cv::Mat(H, W, CV_8UC1, mask01).copyTo(padded(cv::Rect(1, 1, W, H)));
  cv::floodFill(padded, cv::Point(0, 0), cv::Scalar(2), nullptr, cv::Scalar(0), cv::Scalar(0), 4);
  for (int y = 0; y < H; ++y) {
    const std::uint8_t* row = padded.ptr<std::uint8_t>(y + 1) + 1;
    for (int x = 0; x < W; ++x)
      if (row[x] == 0) mask01[std::size_t(y) * W + x] = 1;
  }
}

struct Point {
  std::uint16_t label = 0;
  bool body = false;
  float rgb[3] = {0, 0, 0};
  float hu = -1000;
};

class CtModel {
 public:
  CtModel(const Geometry& g, double skin_px) : g_(g), skin_px_(skin_px) {}

  double hu(const SliceModel& s, double qx, double qy) const {
    // s.ct has one pixel of air around the CT (hence the + 1).
    return bilinear(s.ct, g_.cxct + 1 + (qx - g_.cx) / g_.scale,
                    g_.cyct + 1 + (qy - g_.cy) / g_.scale);
  }

  void eval(const SliceModel& s, double qx, double qy, bool want_rgb, Point& out) const {
    const double h = hu(s, qx, qy);
    out.hu = float(h);
    bool body = false;
    if (h > kBodyHu) {
      // One of the 4 grid pixels around q in the body component.
      const int x0 = int(std::floor(qx)), y0 = int(std::floor(qy));
      for (int dy = 0; dy <= (qy > y0 ? 1 : 0) && !body; ++dy)
        for (int dx = 0; dx <= (qx > x0 ? 1 : 0) && !body; ++dx) {
          const int x = x0 + dx, y = y0 + dy;
          if (x >= 0 && y >= 0 && x < g_.W && y < g_.H && s.mask.at<std::uint8_t>(y, x))
            body = true;
        }
    }
    out.body = body;
    const double depth = body ? bilinear(s.depth, qx, qy) : 0.0;
    std::uint16_t label = kGel;
    if (body) {
      if (depth <= skin_px_)
        label = kSkin;
      else if (h > kBoneHu)
        label = kBone;
      else if (h <= kFatHu)
        label = kFat;
      else
        label = kSoft;
    }
    out.label = label;
    if (!want_rgb) return;
    const double n =
        0.5 * s.tex[0].at(qx, qy) + 0.3 * s.tex[1].at(qx, qy) + 0.2 * s.tex[2].at(qx, qy);
    const double m = s.hue.at(qx, qy);
    double rgb[3];
    if (!body) {
      // Gel, tinted by tissue within a few pixels (translucent), in cavities as well.
      const double gel[3] = {36, 64, 148}, tint[3] = {160, 118, 104};
      const double d = bilinear(s.outside, qx, qy);
      const double through = 0.35 * std::exp(-d / (3.0 * g_.scale));
      for (int i = 0; i < 3; ++i)
        rgb[i] = gel[i] * (1 + 0.05 * n) + through * (tint[i] - gel[i]);
    } else {
      double base[3], texture = 0.08;
      switch (label) {
        case kSkin: {
          const double c[3] = {196, 150, 128};
          std::copy(c, c + 3, base);
          texture = 0.12;
          break;
        }
        case kFat: {
          // Partial volume with air (HU near the threshold) darkens toward a grey-brown edge.
          const double a = smoothstep(kBodyHu, -150.0, h);
          const double edge[3] = {120, 96, 88}, fat[3] = {236, 212, 156};
          for (int i = 0; i < 3; ++i)
            base[i] = edge[i] + a * (fat[i] - edge[i]);
          texture = 0.14;
          break;
        }
        case kBone: {
          const double a = smoothstep(kBoneHu, 800.0, h);  // marrow → cortical bone
          const double marrow[3] = {196, 120, 104}, cortex[3] = {236, 226, 200};
          for (int i = 0; i < 3; ++i)
            base[i] = marrow[i] + a * (cortex[i] - marrow[i]);
          texture = 0.10;
          break;
        }
        default: {
          // Soft tissue: muscle near the surface, brain-like deep inside; CSF-like when HU is low.
          const double deep =
              smoothstep(10.0 * skin_px_ / kSkinMm, 22.0 * skin_px_ / kSkinMm, depth);
          const double muscle[3] = {152, 52, 48}, brain[3] = {206, 176, 164},
                       csf[3] = {176, 144, 146};
          const double wet = smoothstep(20.0, 0.0, h);
          for (int i = 0; i < 3; ++i) {
            const double tissue = muscle[i] + deep * (brain[i] - muscle[i]);
            base[i] = tissue + wet * deep * (csf[i] - tissue);
          }
          texture = 0.22;
          break;
        }
      }
      const double hue[3] = {6 * m, -3 * m, -6 * m};
      for (int i = 0; i < 3; ++i)
        rgb[i] = base[i] * (1 + texture * n) + hue[i];
    }
    for (int i = 0; i < 3; ++i)
      out.rgb[i] = float(rgb[i]);
  }

 private:
  Geometry g_;
  double skin_px_;
};

struct SliceTruth {
  double dx = 0, dy = 0, rot = 0, gain = 1, tilt_x = 0, tilt_y = 0;
  bool jump = false;
};

}  // namespace

CtVolume read_ct_volume(const std::string& path) {
  std::error_code ec;
  if (fs::is_directory(path, ec)) {
    const std::string config = (fs::path(path) / "config.json").string();
    if (!fs::is_regular_file(config, ec))
      throw InputError(cat(path,
                           ": a folder without config.json (give a CT .nrrd, a config file, or a "
                           "sample folder such as data/samples/head-ct)"));
    return read_config_ct(config);
  }
  if (!fs::is_regular_file(path, ec)) throw IoError(cat(path, ": no such file or folder"));
  const std::string ext = fs::path(path).extension().string();
  if (ext == ".nrrd") return read_nrrd_ct(path);
  if (ext == ".json") return read_config_ct(path);
  throw InputError(
      cat(path, ": not a CT volume (expected .nrrd, a config .json, or a sample folder)"));
}

namespace {

// `ct` with every − 1 slices interpolated linearly (in HU, rounded) between each two: slice u of
// the result lies at z = u · spacing / every.
CtVolume interpolate_along_z(const CtVolume& ct, int every) {
  CtVolume fine;
  fine.width = ct.width, fine.height = ct.height;
  fine.slices = (ct.slices - 1) * every + 1;
  fine.spacing_mm = {ct.spacing_mm[0], ct.spacing_mm[1], ct.spacing_mm[2] / every};
  fine.source = ct.source;
  const std::size_t plane = std::size_t(ct.width) * ct.height;
  fine.hu.resize(plane * std::size_t(fine.slices));
  for (int u = 0; u < fine.slices; ++u) {
    const int j = std::min(u / every, ct.slices - 1), r = u - j * every;
    const double w = double(r) / every;
    const std::int16_t* a = ct.slice(j);
    const std::int16_t* b = ct.slice(std::min(j + 1, ct.slices - 1));
    std::int16_t* out = fine.hu.data() + plane * std::size_t(u);
    for (std::size_t i = 0; i < plane; ++i)
      out[i] = static_cast<std::int16_t>(std::lround((1.0 - w) * a[i] + w * b[i]));
  }
  return fine;
}

FromCtSummary make_from_ct(const std::string& out_dir, const CtVolume& ct,
                           const FromCtOptions& options);

}  // namespace

FromCtSummary make_phantom_from_ct(const std::string& out_dir, const CtVolume& ct,
                                   const FromCtOptions& options) {
  if (options.ct_every < 1 || options.ct_every > 10)
    throw UsageError(cat("--ct-every ", options.ct_every, ": must be 1..10"));
  if (options.ct_every == 1) return make_from_ct(out_dir, ct, options);
  if (options.first >= 0 && options.first % options.ct_every != 0)
    throw UsageError(cat("--first ", options.first, ": must be a multiple of --ct-every ",
                         options.ct_every, " (a colour slice on a CT slice)"));
  const CtVolume fine = interpolate_along_z(ct, options.ct_every);
  FromCtOptions o = options;
  if (o.first < 0) {
    const int n = o.slices > 0 ? o.slices : fine.slices;
    o.first = std::max(0, (fine.slices - n) / 2 / o.ct_every * o.ct_every);
  }
  return make_from_ct(out_dir, fine, o);
}

namespace {

FromCtSummary make_from_ct(const std::string& out_dir, const CtVolume& ct,
                           const FromCtOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  const int every = options.ct_every;  // ct: the CT interpolated along z when > 1
  if (ct.width < 8 || ct.height < 8 || ct.slices < 2)
    throw UsageError(
        cat(ct.source, ": CT of ", ct.width, "x", ct.height, "x", ct.slices, " is too small"));
  if (options.scale < 1 || options.scale > 8)
    throw UsageError(cat("--scale ", options.scale, ": must be 1..8"));
  const int N = options.slices > 0 ? options.slices : ct.slices;
  if (options.slices < 0 || N < 2 || N > ct.slices)
    throw UsageError(cat("--slices ", options.slices, ": must be between 2 and ", ct.slices,
                         " (the CT's slices)"));
  const int first = options.first >= 0 ? options.first : (ct.slices - N) / 2;
  if (first + N > ct.slices)
    throw UsageError(
        cat("--first ", first, " with ", N, " slices runs past the CT's ", ct.slices, " slices"));

  Geometry g;
  g.scale = options.scale;
  g.Wct = ct.width, g.Hct = ct.height;
  const int margin = options.margin_px >= 0 ? options.margin_px : 32 * g.scale;
  g.W = ct.width * g.scale + 2 * margin, g.H = ct.height * g.scale + 2 * margin;
  g.cx = (g.W - 1) * 0.5, g.cy = (g.H - 1) * 0.5, g.cxct = (g.Wct - 1) * 0.5,
  g.cyct = (g.Hct - 1) * 0.5;
  g.pixel_mm = ct.spacing_mm[0] / g.scale;
  const int W = g.W, H = g.H;
  const std::size_t plane = std::size_t(W) * H;
  const double skin_px = kSkinMm / g.pixel_mm;
  const CtModel model(g, skin_px);
  const int threads = resolve_threads(options.threads);

  // 1. Per slice: the CT as float, HU on the output grid, components above the threshold.
  std::vector<SliceModel> slices(static_cast<std::size_t>(N));
  std::vector<cv::Mat> comp(static_cast<std::size_t>(N));
  std::vector<int> comp_count(static_cast<std::size_t>(N));
  parallel_for(N, threads, [&](std::int64_t kk) {
    const int k = int(kk);
    SliceModel& s = slices[std::size_t(k)];
    // One pixel of air around the CT: outside its field of view the model is air (−1024 HU).
    cv::Mat hu;
    cv::Mat(g.Hct, g.Wct, CV_16SC1, const_cast<std::int16_t*>(ct.slice(first + k)))
        .convertTo(hu, CV_32F);
    cv::copyMakeBorder(hu, s.ct, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(-1024));
    cv::Mat above(H, W, CV_8UC1);
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x)
        above.at<std::uint8_t>(y, x) = model.hu(s, x, y) > kBodyHu ? 1 : 0;
    comp_count[std::size_t(k)] = cv::connectedComponents(above, comp[std::size_t(k)], 8, CV_32S);
  });
  // 2. The body component: the largest 3-D union of slice components (face-connected in z).
  std::vector<int> offset(std::size_t(N) + 1, 0);
  for (int k = 0; k < N; ++k)
    offset[std::size_t(k) + 1] = offset[std::size_t(k)] + comp_count[std::size_t(k)];
  UnionFind uf;
  uf.parent.resize(std::size_t(offset[std::size_t(N)]));
  std::iota(uf.parent.begin(), uf.parent.end(), 0);
  for (int k = 0; k + 1 < N; ++k) {
    const cv::Mat& a = comp[std::size_t(k)];
    const cv::Mat& b = comp[std::size_t(k) + 1];
    for (int y = 0; y < H; ++y) {
      const int* ra = a.ptr<int>(y);
      const int* rb = b.ptr<int>(y);
      for (int x = 0; x < W; ++x)
        if (ra[x] > 0 && rb[x] > 0)
          uf.join(offset[std::size_t(k)] + ra[x], offset[std::size_t(k) + 1] + rb[x]);
    }
  }
  std::vector<std::int64_t> size(uf.parent.size(), 0);
  for (int k = 0; k < N; ++k) {
    const cv::Mat& a = comp[std::size_t(k)];
    for (int y = 0; y < H; ++y) {
      const int* ra = a.ptr<int>(y);
      for (int x = 0; x < W; ++x)
        if (ra[x] > 0) ++size[std::size_t(uf.find(offset[std::size_t(k)] + ra[x]))];
    }
  }
  const int body_root = int(std::max_element(size.begin(), size.end()) - size.begin());
  if (size.empty() || size[std::size_t(body_root)] == 0)
    throw InputError(
        cat(ct.source, ": nothing above ", kBodyHu, " HU in slices ", first, "..", first + N - 1));
  const double body_fraction = double(size[std::size_t(body_root)]) / (double(plane) * N);

  // 3. Masks, distance maps, texture layers; the body's bounding box over the stack.
  int bx0 = W, bx1 = -1, by0 = H, by1 = -1;
  parallel_for(N, threads, [&](std::int64_t kk) {
    const int k = int(kk);
    SliceModel& s = slices[std::size_t(k)];
    s.mask = cv::Mat::zeros(H, W, CV_8UC1);
    const cv::Mat& a = comp[std::size_t(k)];
    std::vector<std::uint8_t> is_body(static_cast<std::size_t>(comp_count[std::size_t(k)]), 0);
    for (int c = 1; c < comp_count[std::size_t(k)]; ++c)
      is_body[std::size_t(c)] = uf.find(offset[std::size_t(k)] + c) == body_root;
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x) {
        const int c = a.at<int>(y, x);
        if (c > 0 && is_body[std::size_t(c)]) s.mask.at<std::uint8_t>(y, x) = 1;
      }
    cv::distanceTransform(s.mask, s.depth, cv::DIST_L2, cv::DIST_MASK_PRECISE);
    cv::Mat inv = 1 - s.mask;
    cv::distanceTransform(inv, s.outside, cv::DIST_L2, cv::DIST_MASK_PRECISE);
    // Texture: a fresh lattice every slice (scale_slices 1, sampled at integer slices).
    const double pad = 0.3 * std::max(W, H);
    const double scales[3] = {8.0 * g.scale, 3.0 * g.scale, 1.5 * g.scale};
    for (int o = 0; o < 3; ++o)
      s.tex[o] = NoiseLayer(mix64(options.seed * 8 + 1000 + o), scales[o], 1.0, k, -pad, W + pad,
                            -pad, H + pad);
    s.hue = NoiseLayer(mix64(options.seed * 8 + 1100), 12.0 * g.scale, 1.0, k, -pad, W + pad, -pad,
                       H + pad);
  });
  comp.clear();
  for (int k = 0; k < N; ++k) {
    cv::Rect r = cv::boundingRect(slices[std::size_t(k)].mask);
    if (r.area() == 0) continue;
    bx0 = std::min(bx0, r.x), by0 = std::min(by0, r.y);
    bx1 = std::max(bx1, r.x + r.width - 1), by1 = std::max(by1, r.y + r.height - 1);
  }

  // 4. The true transforms: camera offset + random walk + one block jump. Every candidate is
  // checked against the convex hull of the body over the whole stack, so the body never leaves
  // the colour frame (a step that would push it out is reflected, a jump turned elsewhere).
  cv::Mat body_union = cv::Mat::zeros(H, W, CV_8UC1);
  for (int k = 0; k < N; ++k)
    body_union |= slices[std::size_t(k)].mask;
  std::vector<cv::Point> nonzero, hull;
  cv::findNonZero(body_union, nonzero);
  cv::convexHull(nonzero, hull);
  auto fits = [&](double rot, double dx, double dy) {
    const double th = rot * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
    for (const cv::Point& q : hull) {
      // Pixel q covers q ± 0.5: keep kFrameMarginPx plus that half pixel.
      const double x = g.cx + cs * (q.x - g.cx) - sn * (q.y - g.cy) + dx;
      const double y = g.cy + sn * (q.x - g.cx) + cs * (q.y - g.cy) + dy;
      const double m = kFrameMarginPx + 0.5;
      if (x < m || y < m || x > W - 1 - m || y > H - 1 - m) return false;
    }
    return true;
  };
  Random rng(options.seed * 0x9e3779b97f4a7c15ull + 101);
  const double half = g.scale * 0.5;  // sizes below are for scale 2
  const double cam_angle = rng.uniform(0, 2 * kPi);
  double cam_mag = rng.uniform(8.0, 12.0) * half;
  double cam_rot = rng.uniform(1.0, 2.0) * (rng.uniform() < 0.5 ? -1 : 1);
  const int jump_slice = options.jump && N >= 4 ? N / 2 : -1;
  const double jump_mag = rng.uniform(20.0, 35.0) * half, jump_angle = rng.uniform(0, 2 * kPi);
  const double jump_rot = rng.uniform(3.0, 5.0) * (rng.uniform() < 0.5 ? -1 : 1);
  for (int i = 0;
       i < 8 && !fits(cam_rot, cam_mag * std::cos(cam_angle), cam_mag * std::sin(cam_angle)); ++i)
    cam_mag *= 0.5, cam_rot *= 0.5;
  const double cam_dx = cam_mag * std::cos(cam_angle), cam_dy = cam_mag * std::sin(cam_angle);
  if (!fits(cam_rot, cam_dx, cam_dy))
    throw Error(cat("phantom: the body (x ", bx0, "..", bx1, ", y ", by0, "..", by1, ") fills the ",
                    W, "x", H, " frame; use a larger --margin"));
  std::vector<SliceTruth> truth(static_cast<std::size_t>(N));
  double dx = cam_dx, dy = cam_dy, rot = cam_rot;  // the current total transform
  for (int k = 0; k < N; ++k) {
    SliceTruth& t = truth[std::size_t(k)];
    t.gain = 1 + rng.uniform(-kGainRange, kGainRange);
    t.tilt_x = rng.uniform(-kTiltRange, kTiltRange) / W;
    t.tilt_y = rng.uniform(-kTiltRange, kTiltRange) / H;
    const double sx = rng.normal(kDriftPx), sy = rng.normal(kDriftPx), sr = rng.normal(kDriftDeg);
    if (options.drift && k > 0) {
      if (fits(rot + sr, dx + sx, dy + sy)) {
        rot += sr, dx += sx, dy += sy;
      } else if (fits(rot - sr, dx - sx, dy - sy)) {
        rot -= sr, dx -= sx, dy -= sy;
      }
    }
    if (k == jump_slice) {
      bool placed = false;
      for (int attempt = 0; attempt < 48 && !placed; ++attempt) {
        const double mag = jump_mag * (1.0 - 0.15 * (attempt / 16));
        const double r = (attempt / 8) % 2 ? -jump_rot : jump_rot;
        const double a = jump_angle + (attempt % 8) * kPi / 4;
        const double jx = mag * std::cos(a), jy = mag * std::sin(a);
        if (fits(rot + r, dx + jx, dy + jy)) {
          rot += r, dx += jx, dy += jy, placed = true;
        }
      }
      if (!placed)
        throw Error(cat("phantom: no room for a block jump of ", jump_mag, " px in a ", W, "x", H,
                        " frame with the body at x ", bx0, "..", bx1, ", y ", by0, "..", by1,
                        "; use a larger --margin"));
      t.jump = true;
    }
    t.dx = dx, t.dy = dy, t.rot = rot;
  }

  // 5. Render: truth on the output grid; observed colour and seg on each slice's drifted grid.
  const std::string rgb_dir = out_dir + "/rgb", ct_dir = out_dir + "/ct",
                    seg_dir = out_dir + "/seg", truth_dir = out_dir + "/truth";
  for (const auto& d : {rgb_dir, ct_dir, seg_dir, truth_dir})
    make_directories(d);
  const int digits = std::max(4, int(std::to_string(N - 1).size()));
  NrrdVolume t_rgb, t_ct, t_mask, t_labels, t_seg;
  const std::array<double, 3> spacing{g.pixel_mm, g.pixel_mm, ct.spacing_mm[2]};
  auto init = [&](NrrdVolume& v, NrrdType type, int components) {
    v.type = type, v.components = components, v.dims = {W, H, N}, v.spacing_mm = spacing;
    v.data.assign(v.byte_size(), 0);
  };
  init(t_rgb, NrrdType::kUint8, 3);
  init(t_ct, NrrdType::kInt16, 1);
  init(t_mask, NrrdType::kUint8, 1);
  init(t_labels, NrrdType::kUint16, 1);
  init(t_seg, NrrdType::kUint16, 1);
  const GaussianTable gaussian;
  Progress progress("vispack-phantom", N, "slices", options.quiet);
  parallel_for(N, threads, [&](std::int64_t kk) {
    const int k = int(kk);
    const SliceModel& s = slices[std::size_t(k)];
    const SliceTruth& t = truth[std::size_t(k)];
    Point pt;
    auto* o_rgb = t_rgb.as<std::uint8_t>() + plane * 3 * k;
    auto* o_ct = t_ct.as<std::int16_t>() + plane * k;
    auto* o_mask = t_mask.as<std::uint8_t>() + plane * k;
    auto* o_lab = t_labels.as<std::uint16_t>() + plane * k;
    auto* o_seg = t_seg.as<std::uint16_t>() + plane * k;
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x) {
        model.eval(s, x, y, true, pt);
        const std::size_t i = std::size_t(y) * W + x;
        for (int c = 0; c < 3; ++c)
          o_rgb[i * 3 + c] = to_u8(pt.rgb[c]);
        o_ct[i] = static_cast<std::int16_t>(std::clamp(std::lround(pt.hu), -32768L, 32767L));
        o_mask[i] = pt.body ? 1 : 0;
        o_lab[i] = pt.label;
      }
    fill_enclosed_cavities(o_mask, W, H);
    cv::Mat rgb(H, W, CV_8UC3), seg(H, W, CV_8UC3);
    const double th = t.rot * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
    Random noise(mix64(options.seed ^ (0x5851f42d4c957f2dull * std::uint64_t(k + 1))));
    for (int y = 0; y < H; ++y) {
      auto* row = rgb.ptr<std::uint8_t>(y);
      auto* srow = seg.ptr<std::uint8_t>(y);
      for (int x = 0; x < W; ++x) {
        // q = c + R(−θ)(p − c − d), the inverse of p = c + R(θ)(q − c) + d.
        const double px = x - g.cx - t.dx, py = y - g.cy - t.dy;
        const double qx = g.cx + cs * px + sn * py, qy = g.cy - sn * px + cs * py;
        model.eval(s, qx, qy, true, pt);
        const double light = t.gain * (1 + t.tilt_x * (x - g.cx) + t.tilt_y * (y - g.cy));
        float gauss[4];
        noise.normal4(gaussian, gauss);
        for (int c = 0; c < 3; ++c)
          row[x * 3 + c] = to_u8(pt.rgb[c] * light + kNoiseSigma * gauss[c]);
        o_seg[std::size_t(y) * W + x] = pt.label;
        for (int c = 0; c < 3; ++c)
          srow[x * 3 + c] = std::uint8_t(kClasses[pt.label].palette[std::size_t(c)]);
      }
    }
    pipeline::write_image(rgb_dir + "/" + numbered("rgb", k, digits, ".png"), rgb);
    pipeline::write_image(seg_dir + "/" + numbered("seg", k, digits, ".png"), seg);
    // The CT slice as it is: drift-free, its own resolution, stored = HU + 1024.
    cv::Mat ct16(g.Hct, g.Wct, CV_16UC1);
    const std::int16_t* src = ct.slice(first + k);
    for (int y = 0; y < g.Hct; ++y)
      for (int x = 0; x < g.Wct; ++x)
        ct16.at<std::uint16_t>(y, x) = static_cast<std::uint16_t>(
            std::clamp(int(src[std::size_t(y) * g.Wct + x]) + 1024, 0, 65535));
    if ((first + k) % every == 0)  // the CT's own slices only (first is a multiple of every)
      pipeline::write_image(ct_dir + "/" + numbered("ct", k / every, digits, ".png"), ct16);
    progress.advance();
  });
  progress.finish();
  write_nrrd(truth_dir + "/rgb.nrrd", t_rgb);
  write_nrrd(truth_dir + "/ct.nrrd", t_ct);
  write_nrrd(truth_dir + "/mask.nrrd", t_mask);
  write_nrrd(truth_dir + "/labels.nrrd", t_labels);
  write_nrrd(truth_dir + "/seg_labels.nrrd", t_seg);

  detail::TruthTransforms tt;
  tt.width = W, tt.height = H, tt.frame = "ct", tt.has_ct = true;
  tt.ct_scale = g.scale;  // output_frame identity: ct_to_rgb is the pure pixel-size ratio
  tt.extra["margin_px"] = margin;
  for (int k = 0; k < N; ++k) {
    const SliceTruth& t = truth[std::size_t(k)];
    detail::TruthSlice s;
    s.index = k, s.number = k, s.file = numbered("rgb", k, digits, ".png");
    s.dx_px = t.dx, s.dy_px = t.dy, s.rotation_deg = t.rot, s.jump = t.jump, s.gain = t.gain;
    // Observed = colour · gain · (1 + tilt_x·(x − cx) + tilt_y·(y − cy)) + noise (observed px).
    s.extra["light_tilt"] = {t.tilt_x, t.tilt_y};
    tt.slices.push_back(s);
  }
  tt.extra["camera_offset"] = {{"rotation_deg", cam_rot}, {"dx_px", cam_dx}, {"dy_px", cam_dy}};
  tt.extra["noise_sigma"] = kNoiseSigma;
  tt.extra["preset"] = "from-ct";
  tt.extra["seed"] = options.seed;
  tt.extra["source_ct"] = fs::path(ct.source).filename().string();
  tt.extra["first_ct_slice"] = first;
  tt.extra["body_hu"] = kBodyHu;
  detail::write_truth_transforms(truth_dir + "/transforms.json", tt);

  ojson palette;
  palette["labels"] = ojson::array();
  for (int id = 1; id < kCount; ++id)
    palette["labels"].push_back(
        {{"id", id}, {"name", kClasses[id].name}, {"colour", kClasses[id].palette}});
  write_file_atomic(out_dir + "/palette.json", palette.dump(2) + "\n");

  {
    const std::string base = fs::absolute(out_dir).lexically_normal().string();
    pipeline::Config config;
    config.path = base + "/config.json";
    config.name = "phantom-from-ct";
    config.work_dir = base + "/work";
    config.output = base + "/out/volume.vpk";
    config.vdb_output = base + "/out/volume.vdb";
    config.spacing_mm = spacing;
    config.rgb.dir = base + "/rgb";
    config.rgb.pattern = "rgb_{n}.png";
    pipeline::CtSource c;
    c.dir = base + "/ct";
    c.pattern = "ct_{n}.png";
    c.pixel_spacing_mm = {ct.spacing_mm[0], ct.spacing_mm[1]};
    c.slope = 1.0;
    c.intercept = -1024.0;
    if (every > 1) c.slice_spacing_mm = spacing[2] * every;
    config.ct = c;
    pipeline::SegSource sg;
    sg.dir = base + "/seg";
    sg.pattern = "seg_{n}.png";
    sg.palette = base + "/palette.json";
    config.seg = sg;
    config.mask.hu_threshold = kBodyHu;
    pipeline::write_config(out_dir + "/config.json", config);
  }

  FromCtSummary summary;
  summary.width = W, summary.height = H, summary.slices = N;
  summary.ct_width = g.Wct, summary.ct_height = g.Hct, summary.first_ct_slice = first;
  summary.jump_slice = jump_slice;
  summary.body_fraction = body_fraction;
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return summary;
}

}  // namespace

}  // namespace vispack::phantom

// make_phantom_from_ct: colour, seg and truth synthesised from a real CT (from_ct.h).
#include "vispack/phantom/from_ct.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <numeric>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "phantom_folder.h"
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
using detail::file_digits;
using detail::GaussianTable;
using detail::mix64;
using detail::NoiseLayer;
using detail::PaletteEntry;
using detail::PhantomFolder;
using detail::Random;
using detail::to_u8;
using detail::TruthSlice;
using detail::TruthTransforms;
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
    double rgb[3];
    colour(s, qx, qy, body, label, h, depth, rgb);
    for (int i = 0; i < 3; ++i)
      out.rgb[i] = float(rgb[i]);
  }

  // The colour at q of a point of `label` (body or gel) with HU `h` and depth `depth` (px
  // inside the body): the class colour with texture and hue noise; gel tinted by tissue within a
  // few pixels (translucent).
  void colour(const SliceModel& s, double qx, double qy, bool body, std::uint16_t label, double h,
              double depth, double rgb[3]) const {
    const double n =
        0.5 * s.tex[0].at(qx, qy) + 0.3 * s.tex[1].at(qx, qy) + 0.2 * s.tex[2].at(qx, qy);
    const double m = s.hue.at(qx, qy);
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

// The generator of one from-CT phantom folder, step by step (make_from_ct runs the steps in
// order). Holds the CT, the options, the grid and what each step leaves for the next.
class FromCtGenerator {
 public:
  FromCtGenerator(const CtVolume& ct, const FromCtOptions& options)
      : ct_(ct), options_(options), every_(options.ct_every) {
    check_and_size();
  }

  FromCtSummary run(const std::string& out_dir) {
    const auto start = std::chrono::steady_clock::now();
    measure_components();
    find_body_component();
    build_slice_models();
    draw_transforms();
    PhantomFolder folder(out_dir, g_.W, g_.H, n_, spacing(), file_digits(n_));
    render(folder);
    write_truth_and_config(folder);
    FromCtSummary summary;
    summary.width = g_.W, summary.height = g_.H, summary.slices = n_;
    summary.ct_width = g_.Wct, summary.ct_height = g_.Hct, summary.first_ct_slice = first_;
    summary.jump_slice = jump_slice_;
    summary.body_fraction = body_fraction_;
    summary.seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return summary;
  }

 private:
  std::array<double, 3> spacing() const { return {g_.pixel_mm, g_.pixel_mm, ct_.spacing_mm[2]}; }

  // The options against the CT, the slices used and the output grid (ct: the CT interpolated
  // along z when every_ > 1).
  void check_and_size() {
    const CtVolume& ct = ct_;
    if (ct.width < 8 || ct.height < 8 || ct.slices < 2)
      throw UsageError(
          cat(ct.source, ": CT of ", ct.width, "x", ct.height, "x", ct.slices, " is too small"));
    if (options_.scale < 1 || options_.scale > 8)
      throw UsageError(cat("--scale ", options_.scale, ": must be 1..8"));
    n_ = options_.slices > 0 ? options_.slices : ct.slices;
    if (options_.slices < 0 || n_ < 2 || n_ > ct.slices)
      throw UsageError(cat("--slices ", options_.slices, ": must be between 2 and ", ct.slices,
                           " (the CT's slices)"));
    first_ = options_.first >= 0 ? options_.first : (ct.slices - n_) / 2;
    if (first_ + n_ > ct.slices)
      throw UsageError(cat("--first ", first_, " with ", n_, " slices runs past the CT's ",
                           ct.slices, " slices"));
    g_.scale = options_.scale;
    g_.Wct = ct.width, g_.Hct = ct.height;
    margin_ = options_.margin_px >= 0 ? options_.margin_px : 32 * g_.scale;
    g_.W = ct.width * g_.scale + 2 * margin_, g_.H = ct.height * g_.scale + 2 * margin_;
    g_.cx = (g_.W - 1) * 0.5, g_.cy = (g_.H - 1) * 0.5, g_.cxct = (g_.Wct - 1) * 0.5,
    g_.cyct = (g_.Hct - 1) * 0.5;
    g_.pixel_mm = ct.spacing_mm[0] / g_.scale;
    model_ = std::make_unique<CtModel>(g_, kSkinMm / g_.pixel_mm);
    threads_ = resolve_threads(options_.threads);
  }

  // 1. Per slice: the CT as float, HU on the output grid, components above the threshold.
  void measure_components() {
    const int W = g_.W, H = g_.H;
    slices_.resize(static_cast<std::size_t>(n_));
    comp_.resize(static_cast<std::size_t>(n_));
    comp_count_.resize(static_cast<std::size_t>(n_));
    parallel_for(n_, threads_, [&](std::int64_t kk) {
      const int k = int(kk);
      SliceModel& s = slices_[std::size_t(k)];
      // One pixel of air around the CT: outside its field of view the model is air (−1024 HU).
      cv::Mat hu;
      cv::Mat(g_.Hct, g_.Wct, CV_16SC1, const_cast<std::int16_t*>(ct_.slice(first_ + k)))
          .convertTo(hu, CV_32F);
      cv::copyMakeBorder(hu, s.ct, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(-1024));
      cv::Mat above(H, W, CV_8UC1);
      for (int y = 0; y < H; ++y)
        for (int x = 0; x < W; ++x)
          above.at<std::uint8_t>(y, x) = model_->hu(s, x, y) > kBodyHu ? 1 : 0;
      comp_count_[std::size_t(k)] =
          cv::connectedComponents(above, comp_[std::size_t(k)], 8, CV_32S);
    });
  }

  // 2. The body component: the largest 3-D union of slice components (face-connected in z).
  void find_body_component() {
    const int W = g_.W, H = g_.H, N = n_;
    offset_.assign(std::size_t(N) + 1, 0);
    for (int k = 0; k < N; ++k)
      offset_[std::size_t(k) + 1] = offset_[std::size_t(k)] + comp_count_[std::size_t(k)];
    uf_.parent.resize(std::size_t(offset_[std::size_t(N)]));
    std::iota(uf_.parent.begin(), uf_.parent.end(), 0);
    for (int k = 0; k + 1 < N; ++k) {
      const cv::Mat& a = comp_[std::size_t(k)];
      const cv::Mat& b = comp_[std::size_t(k) + 1];
      for (int y = 0; y < H; ++y) {
        const int* ra = a.ptr<int>(y);
        const int* rb = b.ptr<int>(y);
        for (int x = 0; x < W; ++x)
          if (ra[x] > 0 && rb[x] > 0)
            uf_.join(offset_[std::size_t(k)] + ra[x], offset_[std::size_t(k) + 1] + rb[x]);
      }
    }
    std::vector<std::int64_t> size(uf_.parent.size(), 0);
    for (int k = 0; k < N; ++k) {
      const cv::Mat& a = comp_[std::size_t(k)];
      for (int y = 0; y < H; ++y) {
        const int* ra = a.ptr<int>(y);
        for (int x = 0; x < W; ++x)
          if (ra[x] > 0) ++size[std::size_t(uf_.find(offset_[std::size_t(k)] + ra[x]))];
      }
    }
    body_root_ = int(std::max_element(size.begin(), size.end()) - size.begin());
    if (size.empty() || size[std::size_t(body_root_)] == 0)
      throw InputError(cat(ct_.source, ": nothing above ", kBodyHu, " HU in slices ", first_, "..",
                           first_ + N - 1));
    const std::size_t plane = std::size_t(W) * H;
    body_fraction_ = double(size[std::size_t(body_root_)]) / (double(plane) * N);
  }

  // 3. Masks, distance maps, texture layers; the body's bounding box over the stack.
  void build_slice_models() {
    const int W = g_.W, H = g_.H;
    bx0_ = W, bx1_ = -1, by0_ = H, by1_ = -1;
    parallel_for(n_, threads_, [&](std::int64_t kk) {
      const int k = int(kk);
      SliceModel& s = slices_[std::size_t(k)];
      s.mask = cv::Mat::zeros(H, W, CV_8UC1);
      const cv::Mat& a = comp_[std::size_t(k)];
      std::vector<std::uint8_t> is_body(static_cast<std::size_t>(comp_count_[std::size_t(k)]), 0);
      for (int c = 1; c < comp_count_[std::size_t(k)]; ++c)
        is_body[std::size_t(c)] = uf_.find(offset_[std::size_t(k)] + c) == body_root_;
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
      const double scales[3] = {8.0 * g_.scale, 3.0 * g_.scale, 1.5 * g_.scale};
      for (int o = 0; o < 3; ++o)
        s.tex[o] = NoiseLayer(mix64(options_.seed * 8 + 1000 + o), scales[o], 1.0, k, -pad, W + pad,
                              -pad, H + pad);
      s.hue = NoiseLayer(mix64(options_.seed * 8 + 1100), 12.0 * g_.scale, 1.0, k, -pad, W + pad,
                         -pad, H + pad);
    });
    comp_.clear();
    for (int k = 0; k < n_; ++k) {
      cv::Rect r = cv::boundingRect(slices_[std::size_t(k)].mask);
      if (r.area() == 0) continue;
      bx0_ = std::min(bx0_, r.x), by0_ = std::min(by0_, r.y);
      bx1_ = std::max(bx1_, r.x + r.width - 1), by1_ = std::max(by1_, r.y + r.height - 1);
    }
  }

  // The convex hull of the body over the whole stack, which every candidate transform is
  // checked against.
  std::vector<cv::Point> body_hull() const {
    cv::Mat body_union = cv::Mat::zeros(g_.H, g_.W, CV_8UC1);
    for (int k = 0; k < n_; ++k)
      body_union |= slices_[std::size_t(k)].mask;
    std::vector<cv::Point> nonzero, hull;
    cv::findNonZero(body_union, nonzero);
    cv::convexHull(nonzero, hull);
    return hull;
  }

  // 4. The true transforms: camera offset + random walk + one block jump. Every candidate is
  // checked against the convex hull of the body over the whole stack, so the body never leaves
  // the colour frame (a step that would push it out is reflected, a jump turned elsewhere).
  void draw_transforms() {
    const int W = g_.W, H = g_.H, N = n_;
    const std::vector<cv::Point> hull = body_hull();
    auto fits = [&](double rot, double dx, double dy) {
      const double th = rot * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
      for (const cv::Point& q : hull) {
        // Pixel q covers q ± 0.5: keep kFrameMarginPx plus that half pixel.
        const double x = g_.cx + cs * (q.x - g_.cx) - sn * (q.y - g_.cy) + dx;
        const double y = g_.cy + sn * (q.x - g_.cx) + cs * (q.y - g_.cy) + dy;
        const double m = kFrameMarginPx + 0.5;
        if (x < m || y < m || x > W - 1 - m || y > H - 1 - m) return false;
      }
      return true;
    };
    Random rng(options_.seed * 0x9e3779b97f4a7c15ull + 101);
    const double half = g_.scale * 0.5;  // sizes below are for scale 2
    const double cam_angle = rng.uniform(0, 2 * kPi);
    double cam_mag = rng.uniform(8.0, 12.0) * half;
    cam_rot_ = rng.uniform(1.0, 2.0) * (rng.uniform() < 0.5 ? -1 : 1);
    jump_slice_ = options_.jump && N >= 4 ? N / 2 : -1;
    const double jump_mag = rng.uniform(20.0, 35.0) * half, jump_angle = rng.uniform(0, 2 * kPi);
    const double jump_rot = rng.uniform(3.0, 5.0) * (rng.uniform() < 0.5 ? -1 : 1);
    for (int i = 0;
         i < 8 && !fits(cam_rot_, cam_mag * std::cos(cam_angle), cam_mag * std::sin(cam_angle));
         ++i)
      cam_mag *= 0.5, cam_rot_ *= 0.5;
    cam_dx_ = cam_mag * std::cos(cam_angle), cam_dy_ = cam_mag * std::sin(cam_angle);
    if (!fits(cam_rot_, cam_dx_, cam_dy_))
      throw Error(cat("phantom: the body (x ", bx0_, "..", bx1_, ", y ", by0_, "..", by1_,
                      ") fills the ", W, "x", H, " frame; use a larger --margin"));
    truth_.resize(static_cast<std::size_t>(N));
    double dx = cam_dx_, dy = cam_dy_, rot = cam_rot_;  // the current total transform
    for (int k = 0; k < N; ++k) {
      SliceTruth& t = truth_[std::size_t(k)];
      t.gain = 1 + rng.uniform(-kGainRange, kGainRange);
      t.tilt_x = rng.uniform(-kTiltRange, kTiltRange) / W;
      t.tilt_y = rng.uniform(-kTiltRange, kTiltRange) / H;
      const double sx = rng.normal(kDriftPx), sy = rng.normal(kDriftPx), sr = rng.normal(kDriftDeg);
      if (options_.drift && k > 0) {
        if (fits(rot + sr, dx + sx, dy + sy)) {
          rot += sr, dx += sx, dy += sy;
        } else if (fits(rot - sr, dx - sx, dy - sy)) {
          rot -= sr, dx -= sx, dy -= sy;
        }
      }
      if (k == jump_slice_) {
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
                          " frame with the body at x ", bx0_, "..", bx1_, ", y ", by0_, "..", by1_,
                          "; use a larger --margin"));
        t.jump = true;
      }
      t.dx = dx, t.dy = dy, t.rot = rot;
    }
  }

  // 5. Render: truth on the output grid; observed colour and seg on each slice's drifted grid;
  // the CT slices as they are.
  void render(PhantomFolder& folder) const {
    const GaussianTable gaussian;
    Progress progress("vispack-phantom", n_, "slices", options_.quiet);
    parallel_for(n_, threads_, [&](std::int64_t kk) {
      const int k = int(kk);
      render_truth(folder, k);
      render_observed(folder, k, gaussian);
      // The CT slice as it is: drift-free, its own resolution, stored = HU + 1024.
      cv::Mat ct16(g_.Hct, g_.Wct, CV_16UC1);
      const std::int16_t* src = ct_.slice(first_ + k);
      for (int y = 0; y < g_.Hct; ++y)
        for (int x = 0; x < g_.Wct; ++x)
          ct16.at<std::uint16_t>(y, x) = static_cast<std::uint16_t>(
              std::clamp(int(src[std::size_t(y) * g_.Wct + x]) + 1024, 0, 65535));
      if ((first_ + k) % every_ == 0)  // the CT's own slices only (first is a multiple of every)
        folder.write_ct(k / every_, ct16);
      progress.advance();
    });
    progress.finish();
    folder.write_truth_volumes();
  }

  // Slice k of the truth volumes on the output grid.
  void render_truth(PhantomFolder& folder, int k) const {
    const int W = g_.W, H = g_.H;
    const SliceModel& s = slices_[std::size_t(k)];
    Point pt;
    const detail::TruthPlanes truth = folder.truth_planes(k);
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x) {
        model_->eval(s, x, y, true, pt);
        truth.set(std::size_t(y) * W + x, pt.rgb, pt.hu, -32768L, 32767L, pt.body, pt.label);
      }
    fill_enclosed_cavities(truth.mask, W, H);
  }

  // Observed colour and seg slice k on its drifted grid (and the seg IDs as drawn).
  void render_observed(PhantomFolder& folder, int k, const GaussianTable& gaussian) const {
    const int W = g_.W, H = g_.H;
    const SliceModel& s = slices_[std::size_t(k)];
    const SliceTruth& t = truth_[std::size_t(k)];
    Point pt;
    auto* o_seg = folder.truth_seg_labels(k);
    cv::Mat rgb(H, W, CV_8UC3), seg(H, W, CV_8UC3);
    const double th = t.rot * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
    Random noise(mix64(options_.seed ^ (0x5851f42d4c957f2dull * std::uint64_t(k + 1))));
    for (int y = 0; y < H; ++y) {
      auto* row = rgb.ptr<std::uint8_t>(y);
      auto* srow = seg.ptr<std::uint8_t>(y);
      for (int x = 0; x < W; ++x) {
        // q = c + R(−θ)(p − c − d), the inverse of p = c + R(θ)(q − c) + d.
        const double px = x - g_.cx - t.dx, py = y - g_.cy - t.dy;
        const double qx = g_.cx + cs * px + sn * py, qy = g_.cy - sn * px + cs * py;
        model_->eval(s, qx, qy, true, pt);
        const double light = t.gain * (1 + t.tilt_x * (x - g_.cx) + t.tilt_y * (y - g_.cy));
        float gauss[4];
        noise.normal4(gaussian, gauss);
        for (int c = 0; c < 3; ++c)
          row[x * 3 + c] = to_u8(pt.rgb[c] * light + kNoiseSigma * gauss[c]);
        o_seg[std::size_t(y) * W + x] = pt.label;
        for (int c = 0; c < 3; ++c)
          srow[x * 3 + c] = std::uint8_t(kClasses[pt.label].palette[std::size_t(c)]);
      }
    }
    folder.write_rgb(k, ".png", rgb);
    folder.write_seg(k, ".png", seg);
  }

  // truth/transforms.json, palette.json and config.json.
  void write_truth_and_config(const PhantomFolder& folder) const {
    TruthTransforms tt;
    tt.width = g_.W, tt.height = g_.H, tt.frame = "ct", tt.has_ct = true;
    tt.ct_scale = g_.scale;  // output_frame identity: ct_to_rgb is the pure pixel-size ratio
    tt.extra["margin_px"] = margin_;
    for (int k = 0; k < n_; ++k) {
      const SliceTruth& t = truth_[std::size_t(k)];
      TruthSlice s;
      s.index = k, s.number = k, s.file = folder.rgb_name(k, ".png");
      s.dx_px = t.dx, s.dy_px = t.dy, s.rotation_deg = t.rot, s.jump = t.jump, s.gain = t.gain;
      // Observed = colour · gain · (1 + tilt_x·(x − cx) + tilt_y·(y − cy)) + noise (observed px).
      s.extra["light_tilt"] = {t.tilt_x, t.tilt_y};
      tt.slices.push_back(s);
    }
    tt.extra["camera_offset"] = {
        {"rotation_deg", cam_rot_}, {"dx_px", cam_dx_}, {"dy_px", cam_dy_}};
    tt.extra["noise_sigma"] = kNoiseSigma;
    tt.extra["preset"] = "from-ct";
    tt.extra["seed"] = options_.seed;
    tt.extra["source_ct"] = fs::path(ct_.source).filename().string();
    tt.extra["first_ct_slice"] = first_;
    tt.extra["body_hu"] = kBodyHu;
    folder.write_truth_transforms(tt);

    std::vector<PaletteEntry> palette;
    for (int id = 1; id < kCount; ++id)
      palette.push_back({id, kClasses[id].name, kClasses[id].palette});
    folder.write_palette(palette);

    const std::array<double, 3> spacing = this->spacing();
    pipeline::Config config = folder.base_config("phantom-from-ct", ".png",
                                                 {ct_.spacing_mm[0], ct_.spacing_mm[1]}, ".png");
    if (every_ > 1) config.ct->slice_spacing_mm = spacing[2] * every_;
    config.mask.hu_threshold = kBodyHu;
    folder.write_config(config);
  }

  const CtVolume& ct_;
  const FromCtOptions& options_;
  const int every_;  // ct_: the CT interpolated along z when > 1
  int n_ = 0, first_ = 0, margin_ = 0, threads_ = 1;
  Geometry g_;
  std::unique_ptr<CtModel> model_;
  // Steps 1–3: per slice the model, its components above the threshold and the body component.
  std::vector<SliceModel> slices_;
  std::vector<cv::Mat> comp_;
  std::vector<int> comp_count_;
  std::vector<int> offset_;
  UnionFind uf_;
  int body_root_ = 0;
  double body_fraction_ = 0;
  int bx0_ = 0, bx1_ = -1, by0_ = 0, by1_ = -1;  // the body's bounding box (set in step 3)
  // Step 4: the true transforms.
  std::vector<SliceTruth> truth_;
  double cam_rot_ = 0, cam_dx_ = 0, cam_dy_ = 0;
  int jump_slice_ = -1;
};

FromCtSummary make_from_ct(const std::string& out_dir, const CtVolume& ct,
                           const FromCtOptions& options) {
  return FromCtGenerator(ct, options).run(out_dir);
}

}  // namespace

}  // namespace vispack::phantom

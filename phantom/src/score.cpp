// Scoring against the phantom truth (score.h).
#include "vispack/phantom/score.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <limits>

#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"
#include "vispack/pipeline/imaging/slice_io.h"

namespace vispack::phantom {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

cv::Point2d apply(const SliceRigid& t, double x, double y, double cx, double cy) {
  const double th = t.rotation_deg * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
  return {cx + cs * (x - cx) - sn * (y - cy) + t.dx_px,
          cy + sn * (x - cx) + cs * (y - cy) + t.dy_px};
}

double number_at(const json& j, const char* key, const std::string& where) {
  auto it = j.find(key);
  if (it == j.end() || !it->is_number())
    throw FormatError(cat(where, ": \"", key, "\" missing or not a number"));
  return it->get<double>();
}

std::string index_name(const std::string& dir, const std::string& prefix, int k) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%04d", k);
  return dir + "/" + prefix + "_" + buffer + ".png";
}

json nan_to_null(double v) {
  return std::isfinite(v) ? json(v) : json(nullptr);
}

json vector_json(const std::vector<double>& v) {
  json out = json::array();
  for (double x : v)
    out.push_back(nan_to_null(x));
  return out;
}

}  // namespace

double transform_error_px(const SliceRigid& a, const SliceRigid& b, int width, int height) {
  const double cx = (width - 1) * 0.5, cy = (height - 1) * 0.5;
  const double pts[5][2] = {
      {0, 0}, {width - 1.0, 0}, {0, height - 1.0}, {width - 1.0, height - 1.0}, {cx, cy}};
  double worst = 0;
  for (const auto& p : pts) {
    const cv::Point2d pa = apply(a, p[0], p[1], cx, cy), pb = apply(b, p[0], p[1], cx, cy);
    worst = std::max(worst, std::hypot(pa.x - pb.x, pa.y - pb.y));
  }
  return worst;
}

double transform_error_over_px(const SliceRigid& a, const SliceRigid& b, int width, int height,
                               const std::vector<cv::Point>& points) {
  const double cx = (width - 1) * 0.5, cy = (height - 1) * 0.5;
  double worst = 0;
  for (const auto& p : points) {
    const cv::Point2d pa = apply(a, p.x, p.y, cx, cy), pb = apply(b, p.x, p.y, cx, cy);
    worst = std::max(worst, std::hypot(pa.x - pb.x, pa.y - pb.y));
  }
  return worst;
}

SliceRigid relative_to(const SliceRigid& t_k, const SliceRigid& t_r, int, int) {
  const double rot = t_k.rotation_deg - t_r.rotation_deg;
  const double th = rot * kPi / 180.0, cs = std::cos(th), sn = std::sin(th);
  return {rot, t_k.dx_px - (cs * t_r.dx_px - sn * t_r.dy_px),
          t_k.dy_px - (sn * t_r.dx_px + cs * t_r.dy_px)};
}

TransformsFile read_transforms_file(const std::string& path) {
  json j;
  try {
    j = json::parse(read_file(path, std::size_t(256) << 20));
  } catch (const json::exception& e) {
    throw FormatError(cat(path, ": not valid JSON: ", e.what()));
  }
  TransformsFile t;
  t.width = int(number_at(j, "width", path));
  t.height = int(number_at(j, "height", path));
  if (j.contains("frame") && j["frame"].is_string()) t.frame = j["frame"].get<std::string>();
  if (!j.contains("slices") || !j["slices"].is_array())
    throw FormatError(cat(path, ": \"slices\" missing"));
  for (std::size_t k = 0; k < j["slices"].size(); ++k) {
    const json& s = j["slices"][k];
    const std::string where = cat(path, ": slices[", k, "]");
    TransformsFile::Slice out;
    out.t.rotation_deg = number_at(s, "rotation_deg", where);
    out.t.dx_px = number_at(s, "dx_px", where);
    out.t.dy_px = number_at(s, "dy_px", where);
    out.jump = s.value("jump", false);
    out.black = s.value("black", false);
    if (s.contains("duplicate_of") && s["duplicate_of"].is_number_integer())
      out.duplicate_of = s["duplicate_of"].get<int>();
    t.slices.push_back(out);
  }
  if (j.contains("truth_sample")) {
    if (!j["truth_sample"].is_array())
      throw FormatError(cat(path, ": \"truth_sample\" is no array"));
    for (const json& k : j["truth_sample"]) {
      if (!k.is_number_integer() || k.get<long long>() < 0 ||
          k.get<long long>() >= static_cast<long long>(t.slices.size()))
        throw FormatError(cat(path, ": \"truth_sample\" holds ", k.dump(), ", not a slice index"));
      t.truth_sample.push_back(k.get<int>());
    }
  }
  return t;
}

DriftScore score_drift(const TransformsFile& truth, const TransformsFile& estimate) {
  if (truth.width != estimate.width || truth.height != estimate.height ||
      truth.slices.size() != estimate.slices.size())
    throw Error(cat("score: truth is ", truth.width, "x", truth.height, " with ",
                    truth.slices.size(), " slices, the estimate ", estimate.width, "x",
                    estimate.height, " with ", estimate.slices.size()));
  const int W = truth.width, H = truth.height, N = int(truth.slices.size());
  DriftScore d;
  d.error_px.assign(std::size_t(N), kNaN);
  double sum2 = 0, rel2 = 0;
  for (int k = 0; k < N; ++k) {
    const auto& t = truth.slices[std::size_t(k)];
    if (t.black || t.duplicate_of >= 0) continue;  // lost or duplicated: no right answer
    const auto& e = estimate.slices[std::size_t(k)];
    const double err = transform_error_px(e.t, t.t, W, H);
    d.error_px[std::size_t(k)] = err;
    sum2 += err * err, ++d.scored;
    if (err > d.max_px) d.max_px = err, d.max_slice = k;
    const double rel = transform_error_px(relative_to(e.t, estimate.slices[0].t, W, H),
                                          relative_to(t.t, truth.slices[0].t, W, H), W, H);
    rel2 += rel * rel;
    d.relative_max_px = std::max(d.relative_max_px, rel);
  }
  if (d.scored)
    d.rms_px = std::sqrt(sum2 / d.scored), d.relative_rms_px = std::sqrt(rel2 / d.scored);
  return d;
}

JumpScore score_jumps(const TransformsFile& truth, const TransformsFile& estimate) {
  JumpScore j;
  const std::size_t n = std::min(truth.slices.size(), estimate.slices.size());
  for (std::size_t k = 0; k < n; ++k) {
    const bool t = truth.slices[k].jump, e = estimate.slices[k].jump;
    if (t) ++j.true_jumps;
    if (t && e) ++j.found;
    if (t && !e) ++j.missed, j.missed_slices.push_back(int(k));
    if (!t && e) ++j.false_jumps, j.false_slices.push_back(int(k));
  }
  return j;
}

MaskScore score_masks(const NrrdVolume& truth, const std::vector<cv::Mat>& estimate) {
  const int W = int(truth.dims[0]), H = int(truth.dims[1]), N = int(truth.dims[2]);
  if (truth.type != NrrdType::kUint8 || truth.components != 1)
    throw Error("score: truth mask must be uint8 scalar");
  if (int(estimate.size()) != N)
    throw Error(cat("score: ", estimate.size(), " mask slices for a truth of ", N));
  MaskScore m;
  m.iou.assign(std::size_t(N), kNaN);
  std::uint64_t inter_all = 0, union_all = 0;
  double sum_body = 0;
  m.min_body_iou = 1;
  const std::size_t plane = std::size_t(W) * H;
  for (int k = 0; k < N; ++k) {
    const cv::Mat& e = estimate[std::size_t(k)];
    if (e.cols != W || e.rows != H || e.channels() != 1)
      throw Error(cat("score: mask slice ", k, " is ", e.cols, "x", e.rows, "x", e.channels(),
                      ", truth ", W, "x", H));
    cv::Mat e8;
    e.convertTo(e8, CV_8U);  // 16-bit masks: any nonzero stays nonzero after saturation
    const std::uint8_t* t = truth.as<std::uint8_t>() + plane * k;
    std::uint64_t inter = 0, uni = 0, body = 0;
    for (int y = 0; y < H; ++y) {
      const std::uint8_t* er = e8.ptr<std::uint8_t>(y);
      const std::uint8_t* tr = t + std::size_t(y) * W;
      for (int x = 0; x < W; ++x) {
        const bool a = tr[x] != 0, b = er[x] != 0;
        inter += a && b;
        uni += a || b;
        body += a;
      }
    }
    inter_all += inter, union_all += uni;
    if (uni) m.iou[std::size_t(k)] = double(inter) / double(uni);
    if (double(body) >= 0.01 * double(plane)) {
      const double iou = m.iou[std::size_t(k)];
      ++m.body_slices, sum_body += iou;
      if (iou < m.min_body_iou || m.min_body_slice < 0) m.min_body_iou = iou, m.min_body_slice = k;
    }
  }
  m.stack_iou = union_all ? double(inter_all) / double(union_all) : 1.0;
  m.mean_body_iou = m.body_slices ? sum_body / m.body_slices : kNaN;
  if (!m.body_slices) m.min_body_iou = kNaN;
  return m;
}

LabelScore score_labels(const NrrdVolume& truth, const std::vector<cv::Mat>& estimate,
                        const std::vector<int>& excluded, int edge_px) {
  const int W = int(truth.dims[0]), H = int(truth.dims[1]), N = int(truth.dims[2]);
  if (truth.type != NrrdType::kUint16 || truth.components != 1)
    throw Error("score: truth labels must be uint16 scalar");
  if (int(estimate.size()) != N)
    throw Error(cat("score: ", estimate.size(), " label slices for a truth of ", N));
  LabelScore l;
  l.accuracy.assign(std::size_t(N), kNaN);
  l.worst = 1;
  const std::size_t plane = std::size_t(W) * H;
  const cv::Mat kernel =
      cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * edge_px + 1, 2 * edge_px + 1));
  for (int k = 0; k < N; ++k) {
    if (std::find(excluded.begin(), excluded.end(), k) != excluded.end()) continue;
    const cv::Mat& e = estimate[std::size_t(k)];
    if (e.cols != W || e.rows != H || e.channels() != 1)
      throw Error(cat("score: label slice ", k, " is ", e.cols, "x", e.rows, "x", e.channels(),
                      ", truth ", W, "x", H));
    cv::Mat e16;
    e.convertTo(e16, CV_16U);
    const cv::Mat t(H, W, CV_16UC1,
                    const_cast<std::uint16_t*>(truth.as<std::uint16_t>() + plane * k));
    cv::Mat lo, hi;
    cv::erode(t, lo, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
    cv::dilate(t, hi, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
    std::uint64_t counted = 0, equal = 0;
    for (int y = 0; y < H; ++y) {
      const auto* tr = t.ptr<std::uint16_t>(y);
      const auto* er = e16.ptr<std::uint16_t>(y);
      const auto* lr = lo.ptr<std::uint16_t>(y);
      const auto* hr = hi.ptr<std::uint16_t>(y);
      for (int x = 0; x < W; ++x) {
        if (lr[x] != hr[x]) continue;            // within edge_px of a class edge
        if (tr[x] == 0 && er[x] == 0) continue;  // background both: says nothing
        ++counted;
        equal += tr[x] == er[x];
      }
    }
    l.counted += counted, l.equal += equal;
    if (!counted) continue;
    const double a = double(equal) / double(counted);
    l.accuracy[std::size_t(k)] = a;
    ++l.scored_slices;
    if (a < l.worst || l.worst_slice < 0) l.worst = a, l.worst_slice = k;
  }
  l.overall = l.counted ? double(l.equal) / double(l.counted) : kNaN;
  if (!l.scored_slices) l.worst = kNaN;
  return l;
}

namespace {
// A streamed phantom's truth/sample/<prefix>_NNNN.png of the `sample` slices as one volume in
// that order: "mask" as uint8 0/1, "labels" as uint16.
NrrdVolume read_sample_volume(const std::string& truth_dir, const std::string& prefix,
                              const std::vector<int>& sample, const TransformsFile& truth) {
  const bool mask = prefix == "mask";
  NrrdVolume v;
  v.type = mask ? NrrdType::kUint8 : NrrdType::kUint16;
  v.components = 1;
  v.dims = {truth.width, truth.height, int(sample.size())};
  v.data.assign(v.byte_size(), 0);
  const std::size_t plane = std::size_t(truth.width) * truth.height;
  for (std::size_t j = 0; j < sample.size(); ++j) {
    const std::string path = index_name(truth_dir + "/sample", prefix, sample[j]);
    const cv::Mat image = pipeline::read_slice(path);
    if (image.cols != truth.width || image.rows != truth.height || image.channels() != 1 ||
        image.depth() != (mask ? CV_8U : CV_16U))
      throw FormatError(cat(path, ": expected ", truth.width, "x", truth.height,
                            mask ? " 8-bit" : " 16-bit", " grey, got ", image.cols, "x",
                            image.rows));
    const cv::Mat c = image.isContinuous() ? image : image.clone();
    if (mask) {
      std::uint8_t* out = v.as<std::uint8_t>() + plane * j;
      for (std::size_t i = 0; i < plane; ++i)
        out[i] = c.data[i] ? 1 : 0;
    } else {
      std::memcpy(v.as<std::uint16_t>() + plane * j, c.data, plane * 2);
    }
  }
  return v;
}
}  // namespace

Score score_work(const std::string& truth_dir, const std::string& work_dir) {
  Score s;
  const TransformsFile truth = read_transforms_file(truth_dir + "/transforms.json");
  const TransformsFile est = read_transforms_file(work_dir + "/register/transforms.json");
  s.truth_frame = truth.frame, s.estimate_frame = est.frame;
  s.drift = score_drift(truth, est);
  s.jumps = score_jumps(truth, est);
  const int N = int(truth.slices.size());
  // The slices scored for mask, labels and the drift over the body: every one, or a streamed
  // phantom's sample; truth volumes hold exactly these, in this order.
  s.truth_sample = truth.truth_sample;
  const bool sampled = !s.truth_sample.empty();
  std::vector<int> scored(sampled ? s.truth_sample : std::vector<int>{});
  if (!sampled) {
    for (int k = 0; k < N; ++k)
      scored.push_back(k);
  }
  auto read_stack = [&](const std::string& dir, const std::string& prefix,
                        std::vector<cv::Mat>& out) {
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) return false;
    for (int k : scored)
      if (!fs::is_regular_file(index_name(dir, prefix, k), ec)) return false;
    for (int k : scored)
      out.push_back(pipeline::read_slice(index_name(dir, prefix, k)));
    return true;
  };
  const NrrdVolume truth_mask = sampled
                                    ? read_sample_volume(truth_dir, "mask", s.truth_sample, truth)
                                    : read_nrrd(truth_dir + "/mask.nrrd");
  {
    const std::size_t plane = std::size_t(truth_mask.dims[0]) * truth_mask.dims[1];
    double sum2 = 0, sum2_over = 0;
    s.drift.body_max_px = 0;
    s.drift.over_body_max_px = 0;
    std::vector<double> over_body(scored.size(), kNaN);
    for (int j = 0; j < int(scored.size()) && j < truth_mask.dims[2]; ++j) {
      const int k = scored[std::size_t(j)];
      const double e = s.drift.error_px[std::size_t(k)];
      if (!std::isfinite(e)) continue;
      const std::uint8_t* m = truth_mask.as<std::uint8_t>() + plane * std::size_t(j);
      const auto body =
          std::size_t(std::count_if(m, m + plane, [](std::uint8_t v) { return v != 0; }));
      if (body > 0) {
        // Over the truth body: a rigid motion's largest displacement over a set lies on its
        // convex hull.
        const cv::Mat mk(truth_mask.dims[1], truth_mask.dims[0], CV_8UC1,
                         const_cast<std::uint8_t*>(m));
        std::vector<cv::Point> pixels, hull;
        cv::findNonZero(mk, pixels);
        cv::convexHull(pixels, hull);
        const double b =
            transform_error_over_px(est.slices[std::size_t(k)].t, truth.slices[std::size_t(k)].t,
                                    truth.width, truth.height, hull);
        over_body[std::size_t(j)] = b;
        sum2_over += b * b, ++s.drift.over_body_slices;
        if (b > s.drift.over_body_max_px) {
          s.drift.over_body_max_px = b;
          s.drift.over_body_max_slice = k;
        }
      }
      if (double(body) < 0.01 * double(plane)) continue;
      sum2 += e * e, ++s.drift.body_slices;
      s.drift.body_max_px = std::max(s.drift.body_max_px, e);
    }
    s.drift.body_rms_px = s.drift.body_slices ? std::sqrt(sum2 / s.drift.body_slices) : kNaN;
    if (!s.drift.body_slices) s.drift.body_max_px = kNaN;
    s.drift.over_body_px = std::move(over_body);
    s.drift.over_body_rms_px =
        s.drift.over_body_slices ? std::sqrt(sum2_over / s.drift.over_body_slices) : kNaN;
    if (!s.drift.over_body_slices) s.drift.over_body_max_px = kNaN;
  }
  std::vector<cv::Mat> masks, labels;
  if (read_stack(work_dir + "/mask", "mask", masks)) {
    s.has_mask = true;
    s.mask = score_masks(truth_mask, masks);
    if (sampled && s.mask.min_body_slice >= 0)
      s.mask.min_body_slice = scored[std::size_t(s.mask.min_body_slice)];
  }
  if (read_stack(work_dir + "/labels", "labels", labels)) {
    s.has_labels = true;
    std::vector<int> excluded;  // positions in `scored`
    for (int j = 0; j < int(scored.size()); ++j) {
      const auto& t = truth.slices[std::size_t(scored[std::size_t(j)])];
      if (t.black || t.duplicate_of >= 0) excluded.push_back(j);
    }
    s.labels = score_labels(sampled ? read_sample_volume(truth_dir, "labels", s.truth_sample, truth)
                                    : read_nrrd(truth_dir + "/labels.nrrd"),
                            labels, excluded);
    if (sampled && s.labels.worst_slice >= 0)
      s.labels.worst_slice = scored[std::size_t(s.labels.worst_slice)];
  }
  return s;
}

json to_json(const Score& s) {
  json out;
  out["truth_frame"] = s.truth_frame;
  if (!s.truth_sample.empty()) out["truth_sample"] = s.truth_sample;
  out["estimate_frame"] = s.estimate_frame;
  out["drift"] = {{"rms_px", s.drift.rms_px},
                  {"max_px", s.drift.max_px},
                  {"max_slice", s.drift.max_slice},
                  {"scored_slices", s.drift.scored},
                  {"relative_rms_px", s.drift.relative_rms_px},
                  {"relative_max_px", s.drift.relative_max_px},
                  {"body_rms_px", nan_to_null(s.drift.body_rms_px)},
                  {"body_max_px", nan_to_null(s.drift.body_max_px)},
                  {"body_slices", s.drift.body_slices},
                  {"over_body_rms_px", nan_to_null(s.drift.over_body_rms_px)},
                  {"over_body_max_px", nan_to_null(s.drift.over_body_max_px)},
                  {"over_body_max_slice", s.drift.over_body_max_slice},
                  {"over_body_slices", s.drift.over_body_slices},
                  {"over_body_per_slice_px", vector_json(s.drift.over_body_px)},
                  {"per_slice_px", vector_json(s.drift.error_px)}};
  out["jumps"] = {{"true", s.jumps.true_jumps},
                  {"found", s.jumps.found},
                  {"missed", s.jumps.missed},
                  {"false", s.jumps.false_jumps},
                  {"missed_slices", s.jumps.missed_slices},
                  {"false_slices", s.jumps.false_slices}};
  if (s.has_mask) {
    out["mask"] = {{"stack_iou", s.mask.stack_iou},
                   {"body_slices", s.mask.body_slices},
                   {"mean_body_iou", nan_to_null(s.mask.mean_body_iou)},
                   {"min_body_iou", nan_to_null(s.mask.min_body_iou)},
                   {"min_body_slice", s.mask.min_body_slice},
                   {"per_slice_iou", vector_json(s.mask.iou)}};
  }
  if (s.has_labels) {
    out["labels"] = {
        {"accuracy", nan_to_null(s.labels.overall)}, {"counted_px", s.labels.counted},
        {"worst", nan_to_null(s.labels.worst)},      {"worst_slice", s.labels.worst_slice},
        {"scored_slices", s.labels.scored_slices},   {"per_slice", vector_json(s.labels.accuracy)}};
  }
  return out;
}

}  // namespace vispack::phantom

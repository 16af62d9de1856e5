#include "vispack/pipeline/core/transforms.h"

#include <algorithm>
#include <cmath>
#include <filesystem>

#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

cv::Matx23d rigid_matrix(const Rigid& t, cv::Point2d centre) {
  const double a = radians(t.rotation_deg), co = std::cos(a), si = std::sin(a);
  // p = R q + (c − R c + d)
  const double tx = centre.x - (co * centre.x - si * centre.y) + t.dx_px;
  const double ty = centre.y - (si * centre.x + co * centre.y) + t.dy_px;
  return {co, -si, tx, si, co, ty};
}

cv::Matx23d similarity_matrix(const Similarity& t, cv::Point2d c_from, cv::Point2d c_to) {
  const double a = radians(t.rotation_deg);
  const double co = t.scale * std::cos(a), si = t.scale * std::sin(a);
  // q = sR u + (c_to − sR c_from + d)
  const double tx = c_to.x - (co * c_from.x - si * c_from.y) + t.dx_px;
  const double ty = c_to.y - (si * c_from.x + co * c_from.y) + t.dy_px;
  return {co, -si, tx, si, co, ty};
}

cv::Matx23d invert_affine(const cv::Matx23d& m) {
  const double det = m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0);
  if (!(std::abs(det) > 1e-12)) throw Error(cat("invert_affine: singular matrix (det ", det, ")"));
  const double i00 = m(1, 1) / det, i01 = -m(0, 1) / det;
  const double i10 = -m(1, 0) / det, i11 = m(0, 0) / det;
  return {i00, i01, -(i00 * m(0, 2) + i01 * m(1, 2)), i10, i11, -(i10 * m(0, 2) + i11 * m(1, 2))};
}

cv::Matx23d compose_affine(const cv::Matx23d& a, const cv::Matx23d& b) {
  cv::Matx23d r;
  for (int i = 0; i < 2; ++i) {
    for (int j = 0; j < 2; ++j)
      r(i, j) = a(i, 0) * b(0, j) + a(i, 1) * b(1, j);
    r(i, 2) = a(i, 0) * b(0, 2) + a(i, 1) * b(1, 2) + a(i, 2);
  }
  return r;
}

Rigid rigid_from_matrix(const cv::Matx23d& m, cv::Point2d centre) {
  Rigid t;
  t.rotation_deg = degrees(std::atan2(m(1, 0) - m(0, 1), m(0, 0) + m(1, 1)));
  const double px = m(0, 0) * centre.x + m(0, 1) * centre.y + m(0, 2);
  const double py = m(1, 0) * centre.x + m(1, 1) * centre.y + m(1, 2);
  t.dx_px = px - centre.x;
  t.dy_px = py - centre.y;
  return t;
}

Similarity similarity_from_matrix(const cv::Matx23d& m, cv::Point2d c_from, cv::Point2d c_to) {
  Similarity t;
  t.scale = std::sqrt(std::abs(m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0)));
  t.rotation_deg = degrees(std::atan2(m(1, 0) - m(0, 1), m(0, 0) + m(1, 1)));
  const double qx = m(0, 0) * c_from.x + m(0, 1) * c_from.y + m(0, 2);
  const double qy = m(1, 0) * c_from.x + m(1, 1) * c_from.y + m(1, 2);
  t.dx_px = qx - c_to.x;
  t.dy_px = qy - c_to.y;
  return t;
}

cv::Matx23d scale_affine(const cv::Matx23d& m, double scale) {
  // x_s = s·x + o with o = 0.5·s − 0.5 on both sides: m_s = S m S⁻¹.
  const double o = 0.5 * scale - 0.5;
  const cv::Matx23d s{scale, 0, o, 0, scale, o};
  const cv::Matx23d s_inv{1.0 / scale, 0, -o / scale, 0, 1.0 / scale, -o / scale};
  return compose_affine(s, compose_affine(m, s_inv));
}

cv::Matx23d unscale_affine(const cv::Matx23d& m_scaled, double scale) {
  return scale_affine(m_scaled, 1.0 / scale);
}

double rigid_motion_px(const Rigid& t, cv::Size size) {
  const cv::Point2d c = image_centre(size);
  const cv::Matx23d m = rigid_matrix(t, c);
  double worst = 0.0;
  const double xs[3] = {0.0, c.x, size.width - 1.0}, ys[3] = {0.0, c.y, size.height - 1.0};
  for (double x : xs) {
    for (double y : ys) {
      const double px = m(0, 0) * x + m(0, 1) * y + m(0, 2);
      const double py = m(1, 0) * x + m(1, 1) * y + m(1, 2);
      worst = std::max(worst, std::hypot(px - x, py - y));
    }
  }
  return worst;
}

cv::Mat resample_rigid(const cv::Mat& observed, const Rigid& t, int interpolation,
                       const cv::Scalar& border) {
  cv::Mat out;
  cv::warpAffine(observed, out, cv::Mat(rigid_matrix(t, image_centre(observed.size()))),
                 observed.size(), interpolation | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT,
                 border);
  return out;
}

cv::Matx23d output_to_ct(const Similarity& t, cv::Point2d centre, cv::Point2d ct_centre) {
  return invert_affine(similarity_matrix(t, ct_centre, centre));
}

// ---- transforms.json ----

namespace {

template <class T>
T get_key(const nlohmann::json& object, const char* key, const std::string& where, T fallback,
          bool required) {
  auto it = object.find(key);
  if (it == object.end() || it->is_null()) {
    if (required) throw FormatError(cat(where, ": missing key '", key, "'"));
    return fallback;
  }
  try {
    return it->get<T>();
  } catch (const nlohmann::json::exception&) {
    throw FormatError(cat(where, ": key '", key, "' has the wrong type (", it->dump(), ")"));
  }
}

}  // namespace

StackTransforms read_transforms(const std::string& path) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(read_file(path, std::size_t(1) << 30));
  } catch (const nlohmann::json::parse_error& e) {
    throw FormatError(cat(path, ": not valid JSON: ", e.what()));
  }
  if (!j.is_object()) throw FormatError(cat(path, ": not a JSON object"));
  StackTransforms t;
  t.width = get_key<int>(j, "width", path, 0, true);
  t.height = get_key<int>(j, "height", path, 0, true);
  if (t.width <= 0 || t.height <= 0) throw FormatError(cat(path, ": width/height must be > 0"));
  if (j.contains("center_px")) {
    t.center_px = get_key<std::array<double, 2>>(j, "center_px", path, {}, true);
  } else {
    t.center_px = {(t.width - 1) / 2.0, (t.height - 1) / 2.0};
  }
  if (j.contains("reference_slice") && !j["reference_slice"].is_null())
    t.reference_slice = get_key<int>(j, "reference_slice", path, 0, true);
  auto slices = j.find("slices");
  if (slices == j.end() || !slices->is_array())
    throw FormatError(cat(path, ": missing array 'slices'"));
  for (std::size_t i = 0; i < slices->size(); ++i) {
    const auto& s = (*slices)[i];
    std::string where = cat(path, ": slices[", i, "]");
    if (!s.is_object()) throw FormatError(cat(where, ": not an object"));
    SliceTransform st;
    st.index = get_key<int>(s, "index", where, int(i), false);
    if (st.index != int(i)) throw FormatError(cat(where, ": index ", st.index, " out of order"));
    st.number = get_key<int>(s, "number", where, int(i), false);
    st.file = get_key<std::string>(s, "file", where, "", false);
    st.rigid.dx_px = get_key<double>(s, "dx_px", where, 0.0, true);
    st.rigid.dy_px = get_key<double>(s, "dy_px", where, 0.0, true);
    st.rigid.rotation_deg = get_key<double>(s, "rotation_deg", where, 0.0, true);
    st.jump = get_key<bool>(s, "jump", where, false, false);
    st.black = get_key<bool>(s, "black", where, false, false);
    if (s.contains("duplicate_of") && !s["duplicate_of"].is_null())
      st.duplicate_of = get_key<int>(s, "duplicate_of", where, 0, true);
    st.quality = get_key<double>(s, "quality", where, 1.0, false);
    for (auto& [key, value] : s.items()) {
      if (key != "index" && key != "number" && key != "file" && key != "dx_px" && key != "dy_px" &&
          key != "rotation_deg" && key != "jump" && key != "black" && key != "duplicate_of" &&
          key != "quality")
        st.extra[key] = value;
    }
    if (!std::isfinite(st.rigid.dx_px) || !std::isfinite(st.rigid.dy_px) ||
        !std::isfinite(st.rigid.rotation_deg))
      throw FormatError(cat(where, ": transform is not finite"));
    t.slices.push_back(st);
  }
  if (j.contains("ct_to_rgb") && !j["ct_to_rgb"].is_null()) {
    const auto& c = j["ct_to_rgb"];
    std::string where = cat(path, ": ct_to_rgb");
    if (!c.is_object()) throw FormatError(cat(where, ": not an object"));
    Similarity ct;
    ct.scale = get_key<double>(c, "scale", where, 1.0, true);
    ct.rotation_deg = get_key<double>(c, "rotation_deg", where, 0.0, false);
    ct.dx_px = get_key<double>(c, "dx_px", where, 0.0, false);
    ct.dy_px = get_key<double>(c, "dy_px", where, 0.0, false);
    if (!(ct.scale > 0) || !std::isfinite(ct.scale))
      throw FormatError(cat(where, ": scale must be > 0"));
    t.ct_to_rgb = ct;
  }
  for (auto& [key, value] : j.items()) {
    if (key != "width" && key != "height" && key != "center_px" && key != "reference_slice" &&
        key != "slices" && key != "ct_to_rgb")
      t.extra[key] = value;
  }
  return t;
}

std::string transforms_text(const StackTransforms& t) {
  nlohmann::json j = t.extra.is_object() ? t.extra : nlohmann::json::object();
  j["width"] = t.width;
  j["height"] = t.height;
  j["center_px"] = t.center_px;
  j["reference_slice"] = t.reference_slice ? nlohmann::json(*t.reference_slice) : nlohmann::json();
  nlohmann::json slices = nlohmann::json::array();
  for (const auto& s : t.slices) {
    nlohmann::json slice = s.extra.is_object() ? s.extra : nlohmann::json::object();
    slice["index"] = s.index;
    slice["number"] = s.number;
    slice["file"] = s.file;
    slice["dx_px"] = s.rigid.dx_px;
    slice["dy_px"] = s.rigid.dy_px;
    slice["rotation_deg"] = s.rigid.rotation_deg;
    slice["jump"] = s.jump;
    slice["black"] = s.black;
    slice["duplicate_of"] = s.duplicate_of ? nlohmann::json(*s.duplicate_of) : nlohmann::json();
    slice["quality"] = s.quality;
    slices.push_back(std::move(slice));
  }
  j["slices"] = std::move(slices);
  if (t.ct_to_rgb) {
    j["ct_to_rgb"] = {{"scale", t.ct_to_rgb->scale},
                      {"rotation_deg", t.ct_to_rgb->rotation_deg},
                      {"dx_px", t.ct_to_rgb->dx_px},
                      {"dy_px", t.ct_to_rgb->dy_px}};
  }
  return j.dump(2) + "\n";
}

void write_transforms(const std::string& path, const StackTransforms& t) {
  make_directories(fs::path(path).parent_path().string());
  write_file_atomic(path, transforms_text(t));
}

}  // namespace vispack::pipeline

// Body and gel outlines from CT and colour slices. See outline.h.
#include "vispack/pipeline/imaging/outline.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "vispack/common/error.h"
#include "vispack/common/math_constants.h"

namespace vispack::pipeline {
namespace {

cv::Mat disc(int radius) {
  return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
}

// Distance (pixels) of each mask pixel to the nearest pixel outside it, where everything beyond
// the image counts as outside (cv::distanceTransform alone ignores the image border).
cv::Mat inside_distance(const cv::Mat& mask) {
  cv::Mat padded, dist;
  cv::copyMakeBorder(mask, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::distanceTransform(padded, dist, cv::DIST_L2, cv::DIST_MASK_5);
  return dist(cv::Rect(1, 1, mask.cols, mask.rows));
}

}  // namespace

cv::Mat ct_hu_float(const cv::Mat& ct_hu) {
  if (ct_hu.type() == CV_32FC1) return ct_hu;
  if (ct_hu.channels() != 1) throw InputError(cat("CT slice has ", ct_hu.channels(), " channels"));
  cv::Mat f;
  ct_hu.convertTo(f, CV_32F);
  return f;
}

void require_rgb_slice(const cv::Mat& rgb, const char* what) {
  if (rgb.empty() || rgb.type() != CV_8UC3)
    throw InputError(cat(what, ": expected an 8-bit RGB slice, got type ", rgb.type()));
}

namespace {

// Per part (labels 1..n-1 of `labels` over `m`, the mask's box), the measures the part rule reads.
struct PartMeasures {
  std::vector<double> inscribed;      // largest inscribed radius, px (rule.max_elongation > 0 only)
  std::vector<cv::Vec3d> colour_sum;  // summed RGB (a colour slice only)
  std::vector<double> median_hu;      // CT parts only the soft-tissue exception could keep
};

std::vector<double> inscribed_radii(const cv::Mat& m, const cv::Mat& labels, int n) {
  std::vector<double> inscribed(std::size_t(n), 0.0);
  const cv::Mat dist = inside_distance(m);
  for (int y = 0; y < m.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    const float* d = dist.ptr<float>(y);
    for (int x = 0; x < m.cols; ++x)
      if (l[x] > 0)
        inscribed[std::size_t(l[x])] = std::max(inscribed[std::size_t(l[x])], double(d[x]));
  }
  return inscribed;
}

std::vector<cv::Vec3d> colour_sums(const cv::Mat& rgb_box, const cv::Mat& labels, int n) {
  std::vector<cv::Vec3d> colour(std::size_t(n), cv::Vec3d(0, 0, 0));
  for (int y = 0; y < labels.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    const cv::Vec3b* p = rgb_box.ptr<cv::Vec3b>(y);
    for (int x = 0; x < labels.cols; ++x)
      if (l[x] > 0) colour[std::size_t(l[x])] += cv::Vec3d(p[x][0], p[x][1], p[x][2]);
  }
  return colour;
}

// The median HU of each part with wanted[i] set (1e9 for the others).
std::vector<double> median_hu_of(const cv::Mat& hu_box, const cv::Mat& labels,
                                 const std::vector<std::uint8_t>& wanted) {
  const std::size_t n = wanted.size();
  std::vector<double> median(n, 1e9);
  std::vector<std::vector<float>> values(n);
  for (int y = 0; y < labels.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    const float* v = hu_box.ptr<float>(y);
    for (int x = 0; x < labels.cols; ++x)
      if (wanted[std::size_t(l[x])]) values[std::size_t(l[x])].push_back(v[x]);
  }
  for (std::size_t i = 1; i < n; ++i) {
    auto& v = values[i];
    if (v.empty()) continue;
    std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
    median[i] = v[v.size() / 2];
  }
  return median;
}

}  // namespace

cv::Mat body_parts(const cv::Mat& mask, const PartRule& rule, PartCounts* counts,
                   const cv::Mat& rgb, const cv::Mat& hu) {
  if (!rgb.empty()) {
    require_rgb_slice(rgb, "body_parts");
    if (rgb.size() != mask.size()) throw Error("body_parts: mask and slice differ in size");
  }
  if (!hu.empty() && (hu.size() != mask.size() || hu.type() != CV_32FC1))
    throw Error("body_parts: mask and CT slice differ in size (or the CT is not CV_32F)");
  if (counts) *counts = {};
  cv::Mat out = cv::Mat::zeros(mask.size(), CV_8UC1);
  // Only the parts' bounding box is examined.
  const cv::Rect box = cv::boundingRect(mask);
  if (box.empty()) return out;
  cv::Mat labels, stats, centroids;
  const cv::Mat m = mask(box) > 0;
  const int n = cv::connectedComponentsWithStats(m, labels, stats, centroids, 8, CV_32S);
  if (n <= 1) return out;
  PartMeasures pm;
  pm.inscribed = rule.max_elongation > 0 ? inscribed_radii(m, labels, n)
                                         : std::vector<double>(std::size_t(n), 0.0);
  if (!rgb.empty()) pm.colour_sum = colour_sums(rgb(box), labels, n);
  // Elongation per part (the distance transform counts from the pixel centre to the nearest
  // outside centre: a disc of radius R reads about R + 0.5).
  auto elongation = [&](int i) {
    const double r = std::max(0.5, pm.inscribed[std::size_t(i)]);
    return stats.at<int>(i, cv::CC_STAT_AREA) / (kPi * r * r);
  };
  // The median HU of the CT parts that only the soft-tissue exception could keep.
  pm.median_hu.assign(std::size_t(n), 1e9);
  if (!hu.empty() && rule.max_elongation > 0) {
    std::vector<std::uint8_t> wanted(static_cast<std::size_t>(n), 0);
    bool any = false;
    for (int i = 1; i < n; ++i) {
      const double e = elongation(i);
      if (e > rule.max_elongation && e <= kMaxTissueElongation)
        wanted[std::size_t(i)] = 1, any = true;
    }
    if (any) pm.median_hu = median_hu_of(hu(box), labels, wanted);
  }
  std::vector<std::uint8_t> keep(std::size_t(n), 0);
  int kept = 0;
  for (int i = 1; i < n; ++i) {
    const double area = stats.at<int>(i, cv::CC_STAT_AREA);
    bool body = area >= rule.min_area_px;
    if (body && rule.max_elongation > 0)
      body =
          elongation(i) <= rule.max_elongation || pm.median_hu[std::size_t(i)] <= kSoftTissueMaxHu;
    if (body && !rgb.empty()) {
      const cv::Vec3d mean = pm.colour_sum[std::size_t(i)] / area;
      body = mean[1] <= mean[0] + kTissueColourSlack && mean[2] <= mean[0] + kTissueColourSlack;
    }
    keep[std::size_t(i)] = body ? 255 : 0;
    kept += body ? 1 : 0;
  }
  if (counts) *counts = {kept, n - 1 - kept};
  cv::Mat o = out(box);
  for (int y = 0; y < m.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    std::uint8_t* po = o.ptr<std::uint8_t>(y);
    for (int x = 0; x < m.cols; ++x)
      po[x] = keep[std::size_t(l[x])];
  }
  return out;
}

cv::Mat fill_holes(const cv::Mat& mask) {
  // Flood the background from a 1-pixel frame around the image; what stays 0 is a hole.
  cv::Mat padded;
  cv::copyMakeBorder(mask > 0, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::floodFill(padded, cv::Point(0, 0), cv::Scalar(128), nullptr, cv::Scalar(0), cv::Scalar(0), 4);
  cv::Mat inner = padded(cv::Rect(1, 1, mask.cols, mask.rows));
  return inner != 128;
}

cv::Mat open_disc(const cv::Mat& mask, int radius) {
  if (radius <= 0) return mask.clone();
  cv::Mat out;
  cv::morphologyEx(mask, out, cv::MORPH_OPEN, disc(radius));
  return out;
}

cv::Mat ct_tissue(const cv::Mat& ct_hu, double hu_threshold) {
  return fill_holes(ct_hu_float(ct_hu) > hu_threshold);
}

namespace {

// Continuity along z (outline.h): adds to `body` every part of `raw` that holds no body pixel,
// is not thin and long, and has at least a quarter of its pixels on tissue in `z.needed` of the
// neighbours. Returns the number of parts added.
int add_continuing_parts(const cv::Mat& raw, const cv::Mat& hu, const ZNeighbours& z,
                         cv::Mat& body) {
  for (const cv::Mat& t : z.tissue)
    if (t.size() != raw.size())
      throw Error(cat("ct_body_mask: a neighbouring CT slice is ", t.cols, "x", t.rows,
                      ", the slice ", raw.cols, "x", raw.rows));
  if (z.tissue.empty() || int(z.tissue.size()) < z.needed) return 0;
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(raw, labels, stats, centroids, 8, CV_32S);
  if (n <= 1) return 0;
  // Per part: holds body, pixels on each neighbour's tissue, largest inscribed radius.
  std::vector<std::uint8_t> has_body(std::size_t(n), 0);
  std::vector<std::vector<int>> on(z.tissue.size(), std::vector<int>(std::size_t(n), 0));
  for (int y = 0; y < raw.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    const std::uint8_t* b = body.ptr<std::uint8_t>(y);
    for (int x = 0; x < raw.cols; ++x) {
      if (l[x] == 0) continue;
      if (b[x]) has_body[std::size_t(l[x])] = 1;
      for (std::size_t t = 0; t < z.tissue.size(); ++t)
        if (z.tissue[t].ptr<std::uint8_t>(y)[x]) ++on[t][std::size_t(l[x])];
    }
  }
  std::vector<std::uint8_t> add(std::size_t(n), 0);
  bool any = false;
  for (int i = 1; i < n; ++i) {
    if (has_body[std::size_t(i)]) continue;
    const int area = stats.at<int>(i, cv::CC_STAT_AREA);
    int continues = 0;
    for (const auto& o : on)
      continues += 4 * o[std::size_t(i)] >= area ? 1 : 0;
    if (continues >= z.needed) add[std::size_t(i)] = 1, any = true;
  }
  if (!any) return 0;
  // Not thin and long (a holder or table continues along z too): the part rule's shape test.
  cv::Mat candidates = cv::Mat::zeros(raw.size(), CV_8UC1);
  for (int y = 0; y < raw.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    std::uint8_t* c = candidates.ptr<std::uint8_t>(y);
    for (int x = 0; x < raw.cols; ++x)
      if (add[std::size_t(l[x])]) c[x] = 255;
  }
  PartCounts added;
  body |= body_parts(candidates, PartRule{}, &added, cv::Mat(), hu);
  return added.kept;
}

// The steps of ct_body_mask after the opening, on the box around the kept parts.

// The shaved-off set: threshold pixels (`raw_box`) outside the kept parts, in pieces
// (8-connected).
struct ShavedPieces {
  cv::Mat labels, stats, centroids;
};

ShavedPieces shaved_pieces(const cv::Mat& raw_box, const cv::Mat& kept) {
  ShavedPieces p;
  cv::connectedComponentsWithStats(raw_box & ~kept, p.labels, p.stats, p.centroids, 8, CV_32S);
  return p;
}

// A fragment of a holder: the opening leaves spots of a band slightly thicker than its disc as
// small parts. Such a part is thin (its largest inscribed radius at most kThinPartPx) and
// touches a shaved-off piece larger than itself (the band it sat on); a small part of its own (a
// toe, a finger tip) loses only a rim thinner than itself. Fragments leave `kept` (and count as
// removed); the pieces are recomputed when any did.
void drop_holder_fragments(cv::Mat& kept, const cv::Mat& raw_box, ShavedPieces& pieces,
                           PartCounts* counts) {
  constexpr float kThinPartPx = kCtDetachPx + 1.5f;
  cv::Mat parts, part_stats, part_centroids;
  const int np =
      cv::connectedComponentsWithStats(kept, parts, part_stats, part_centroids, 8, CV_32S);
  const cv::Mat inside = inside_distance(kept);
  std::vector<float> radius(std::size_t(np), 0.f);
  for (int y = 0; y < kept.rows; ++y) {
    const int* l = parts.ptr<int>(y);
    const float* d = inside.ptr<float>(y);
    for (int x = 0; x < kept.cols; ++x)
      radius[std::size_t(l[x])] = std::max(radius[std::size_t(l[x])], d[x]);
  }
  std::vector<std::uint8_t> fragment(std::size_t(np), 0);
  bool any = false;
  for (int y = 0; y < kept.rows; ++y) {
    const int* l = parts.ptr<int>(y);
    for (int x = 0; x < kept.cols; ++x) {
      const int part = l[x];
      if (part == 0 || radius[std::size_t(part)] > kThinPartPx || fragment[std::size_t(part)])
        continue;
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          const int yy = y + dy, xx = x + dx;
          if (yy < 0 || xx < 0 || yy >= kept.rows || xx >= kept.cols) continue;
          const int piece = pieces.labels.at<int>(yy, xx);
          if (piece > 0 && pieces.stats.at<int>(piece, cv::CC_STAT_AREA) >
                               part_stats.at<int>(part, cv::CC_STAT_AREA))
            fragment[std::size_t(part)] = 1, any = true;
        }
    }
  }
  if (!any) return;
  kept = kept.clone();
  for (int y = 0; y < kept.rows; ++y) {
    const int* l = parts.ptr<int>(y);
    std::uint8_t* k = kept.ptr<std::uint8_t>(y);
    for (int x = 0; x < kept.cols; ++x)
      if (fragment[std::size_t(l[x])]) k[x] = 0;
  }
  for (int i = 1; i < np; ++i)
    if (fragment[std::size_t(i)] && counts) --counts->kept, ++counts->removed;
  pieces = shaved_pieces(raw_box, kept);
}

// Where each shaved-off piece lies: `near`, the regrowth's reach (a disc of `reach` around the
// kept parts); per piece, whether it touches a kept part (within one pixel, 8-neighbours) and
// whether any of it lies beyond kHolderReachPx of one (the box's edge lies beyond
// kHolderReachPx, so a piece the box cuts reaches beyond too).
struct PieceReach {
  cv::Mat near;
  std::vector<std::uint8_t> touches, beyond;
};

PieceReach classify_pieces(const cv::Mat& kept, const ShavedPieces& pieces, int reach) {
  PieceReach r;
  cv::Mat distance;
  cv::dilate(kept, r.near, disc(reach));
  cv::distanceTransform(~kept, distance, cv::DIST_L2, cv::DIST_MASK_5);
  const cv::Mat far = distance <= float(kHolderReachPx), touch = distance < 1.5f;
  r.touches.assign(std::size_t(pieces.stats.rows), 0);
  r.beyond.assign(std::size_t(pieces.stats.rows), 0);
  for (int y = 0; y < kept.rows; ++y) {
    const int* l = pieces.labels.ptr<int>(y);
    const std::uint8_t* t = touch.ptr<std::uint8_t>(y);
    const std::uint8_t* f = far.ptr<std::uint8_t>(y);
    for (int x = 0; x < kept.cols; ++x) {
      if (l[x] == 0) continue;
      if (t[x]) r.touches[std::size_t(l[x])] = 1;
      if (!f[x]) r.beyond[std::size_t(l[x])] = 1;
    }
  }
  return r;
}

// Where a holder or table touches a part, the opening's disc still fits into the corner between
// them and keeps a fillet of the holder in the part (an arm resting on the table: its lower edge
// a CT pixel too low, which turned the CT anchor by 0.25° on the male phantom). The holder (the
// pieces that touch a part and reach beyond kHolderReachPx), one pixel wider, is taken out of
// the threshold and the opening repeated: the fillet goes, the part's own edge stays. The pieces
// and their reach are recomputed when there was a holder.
void cut_holder_fillets(cv::Mat& kept, const cv::Mat& raw_box, ShavedPieces& pieces,
                        PieceReach& where, int reach) {
  cv::Mat holder = cv::Mat::zeros(kept.size(), CV_8UC1);
  bool any = false;
  for (int y = 0; y < kept.rows; ++y) {
    const int* l = pieces.labels.ptr<int>(y);
    std::uint8_t* o = holder.ptr<std::uint8_t>(y);
    for (int x = 0; x < kept.cols; ++x)
      if (l[x] > 0 && where.touches[std::size_t(l[x])] && where.beyond[std::size_t(l[x])])
        o[x] = 255, any = true;
  }
  if (!any) return;
  cv::dilate(holder, holder, cv::Mat());
  kept = kept & open_disc(raw_box & ~holder, kCtDetachPx);
  pieces = shaved_pieces(raw_box, kept);
  where = classify_pieces(kept, pieces, reach);
}

// The kept parts plus every shaved-off piece that touches one and lies wholly within
// kHolderReachPx of one, within the regrowth's reach.
cv::Mat regrow_shaved_edge(const cv::Mat& kept, const ShavedPieces& pieces,
                           const PieceReach& where) {
  cv::Mat grown = kept.clone();
  for (int y = 0; y < kept.rows; ++y) {
    const int* l = pieces.labels.ptr<int>(y);
    const std::uint8_t* nr = where.near.ptr<std::uint8_t>(y);
    std::uint8_t* g = grown.ptr<std::uint8_t>(y);
    for (int x = 0; x < kept.cols; ++x)
      if (l[x] > 0 && nr[x] && where.touches[std::size_t(l[x])] && !where.beyond[std::size_t(l[x])])
        g[x] = 255;
  }
  return grown;
}

}  // namespace

cv::Mat ct_body_mask(const cv::Mat& ct_hu, double hu_threshold, double min_part_px,
                     PartCounts* counts, const ZNeighbours* z) {
  cv::Mat hu = ct_hu_float(ct_hu);
  // Holes filled first: a cavity near the body's edge (a sinus, an airway) leaves only a thin
  // band of tissue between it and the outside, which the opening below would cut off with the
  // holder (at the ends of the stack, where the body is a few CT pixels across, half the body).
  cv::Mat raw = fill_holes(hu > hu_threshold);
  // The opening cuts thin bridges (head-holder, table); every part that is body stays
  // (outline.h: the part rule).
  PartRule rule;
  rule.min_area_px = min_part_px;
  cv::Mat body = body_parts(open_disc(raw, kCtDetachPx), rule, counts, cv::Mat(), hu);
  // Continuity along z: the parts the opening or the minimum area dropped that continue into the
  // neighbouring CT slices (none of them touches a kept part: the regrowth below leaves them).
  auto continuing = [&](cv::Mat& mask) {
    if (!z) return;
    const int added = add_continuing_parts(raw, hu, *z, mask);
    if (counts && added > 0)
      counts->kept += added, counts->removed = std::max(0, counts->removed - added);
  };
  const cv::Rect bounds = cv::boundingRect(body);
  if (bounds.empty()) {
    continuing(body);
    return body;
  }
  // Grow back what the opening shaved off the parts' own edge, only within its radius + 1, and
  // none of a shaved-off piece that reaches beyond kHolderReachPx (a holder or table touching a
  // part). All of it lies within the parts' bounding box grown by kHolderReachPx; one more pixel
  // of background around it lets fill_holes work on the box alone.
  const int reach = kCtDetachPx + 1, m = kHolderReachPx + 2;
  const cv::Rect box =
      cv::Rect(bounds.x - m, bounds.y - m, bounds.width + 2 * m, bounds.height + 2 * m) &
      cv::Rect(0, 0, body.cols, body.rows);
  cv::Mat kept = body(box);
  const cv::Mat raw_box = raw(box);
  ShavedPieces pieces = shaved_pieces(raw_box, kept);
  drop_holder_fragments(kept, raw_box, pieces, counts);
  PieceReach where = classify_pieces(kept, pieces, reach);
  cut_holder_fillets(kept, raw_box, pieces, where, reach);
  cv::Mat out = cv::Mat::zeros(body.size(), CV_8UC1);
  fill_holes(regrow_shaved_edge(kept, pieces, where)).copyTo(out(box));
  continuing(out);
  return out;
}

cv::Vec3f estimate_gel_colour(const cv::Mat& rgb) {
  require_rgb_slice(rgb, "estimate_gel_colour");
  const int band = std::max(1, std::min({4, rgb.cols / 4, rgb.rows / 4}));
  std::vector<int> channel[3];
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3b* row = rgb.ptr<cv::Vec3b>(y);
    const bool edge_row = y < band || y >= rgb.rows - band;
    for (int x = 0; x < rgb.cols; ++x) {
      if (!edge_row && x >= band && x < rgb.cols - band) {
        x = rgb.cols - band - 1;
        continue;
      }
      for (int c = 0; c < 3; ++c)
        channel[c].push_back(row[x][c]);
    }
  }
  cv::Vec3f gel;
  for (int c = 0; c < 3; ++c) {
    auto mid = channel[c].begin() + channel[c].size() / 2;
    std::nth_element(channel[c].begin(), mid, channel[c].end());
    gel[c] = float(*mid);
  }
  return gel;
}

cv::Mat non_gel(const cv::Mat& rgb, const cv::Vec3f& gel, double distance) {
  require_rgb_slice(rgb, "non_gel");
  cv::Mat out(rgb.size(), CV_8UC1);
  const int g0 = int(std::lround(gel[0])), g1 = int(std::lround(gel[1])),
            g2 = int(std::lround(gel[2]));
  const int limit = int(std::floor(distance * distance));
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3b* in = rgb.ptr<cv::Vec3b>(y);
    std::uint8_t* o = out.ptr<std::uint8_t>(y);
    for (int x = 0; x < rgb.cols; ++x) {
      const int a = in[x][0] - g0, b = in[x][1] - g1, c = in[x][2] - g2;
      o[x] = (a * a + b * b + c * c > limit) ? 255 : 0;
    }
  }
  return out;
}

cv::Mat colour_body_mask(const cv::Mat& rgb, const cv::Vec3f& gel, double distance, int opening_px,
                         double min_part_px, PartCounts* counts) {
  PartRule rule;
  rule.min_area_px = min_part_px;
  // Holes filled before the rule, which judges a part by its outline.
  return body_parts(fill_holes(open_disc(non_gel(rgb, gel, distance), opening_px)), rule, counts,
                    rgb);
}

}  // namespace vispack::pipeline

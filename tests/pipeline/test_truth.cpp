// The packed file against the phantom's truth (docs/GOALS.md §6: "the packed file's channels agree
// with truth/ within stated tolerances"). The whole pipeline (register, mask, labels, pack) runs on
// a `small` phantom cut to 24 slices (256x192, the small preset's pixel and CT sizes, the block
// jump, one black and one duplicated slice), and every channel of the packed file is compared with
// truth/ voxel by voxel. The tolerances come from the pipeline's goals, not from what today's
// code measures: the mask goal is IoU >= 0.99 and the registration goal a drift error <= 0.1 px
// (docs/GOALS.md §6). Where the code misses a goal the test fails and says by how
// much.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <set>

#include <nlohmann/json.hpp>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "test_support.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/nrrd.h"
#include "vispack/format/reader.h"
#include "vispack/phantom/phantom.h"
#include "vispack/pipeline/core/stage_run.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/slice_io.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/run/run.h"

using namespace vispack;
using namespace vispack::pipeline;
using namespace vispack::phantom;

namespace {

constexpr int kSlices = 24;

// Pixels whose truth label is constant over a (2r+1)^2 window (away from every boundary).
cv::Mat uniform_within(const cv::Mat& labels16, int r) {
  cv::Mat lab, lo, hi;
  labels16.convertTo(lab, CV_32F);
  const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * r + 1, 2 * r + 1));
  cv::erode(lab, lo, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  cv::dilate(lab, hi, kernel, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  return lo == hi;
}

struct PackedVsTruth {
  // Alpha (>= 128) against truth/mask.nrrd.
  std::uint64_t inter = 0, uni = 0;
  // Colour inside the truth mask, per channel, gain divided out: all, and away from label edges.
  double rgb_abs = 0, rgb_abs_inner = 0;
  std::uint64_t rgb_n = 0, rgb_n_inner = 0;
  // CT inside the truth mask: all, and where the truth CT is flat over +-2 CT pixels.
  double ct_abs = 0, ct_abs_flat = 0;
  std::uint64_t ct_n = 0, ct_n_flat = 0;
  // Labels: inside the mask, and away from label edges (truth 3x3 uniform).
  std::uint64_t lab_body = 0, lab_body_eq = 0, lab_inner = 0, lab_inner_wrong = 0;
  double iou() const { return uni ? double(inter) / uni : 0; }
  double rgb_mae = 0, rgb_mae_inner = 0, ct_mae = 0, ct_mae_flat = 0;
  double lab_body_fraction = 0, lab_inner_wrong_fraction = 0;
  void finish() {
    rgb_mae = rgb_abs / double(std::max<std::uint64_t>(rgb_n, 1));
    rgb_mae_inner = rgb_abs_inner / double(std::max<std::uint64_t>(rgb_n_inner, 1));
    ct_mae = ct_abs / double(std::max<std::uint64_t>(ct_n, 1));
    ct_mae_flat = ct_abs_flat / double(std::max<std::uint64_t>(ct_n_flat, 1));
    lab_body_fraction = double(lab_body_eq) / double(std::max<std::uint64_t>(lab_body, 1));
    lab_inner_wrong_fraction =
        double(lab_inner_wrong) / double(std::max<std::uint64_t>(lab_inner, 1));
  }
};

// The small preset cut to kSlices slices, with its defects (black + duplicated slice).
Config make_small_phantom(const test::TempDir& dir) {
  PhantomOptions po;
  po.preset = "small";
  po.slices = kSlices;
  po.seed = 3;
  po.defects = true;
  po.quiet = true;
  make_phantom(dir.path(), po);
  return load_config(dir / "config.json");
}

// Reads the packed file (config.output) and compares it with dir/truth, voxel by voxel.
PackedVsTruth compare_packed_with_truth(const test::TempDir& dir, const Config& config,
                                        const std::string& what) {
  auto reader = format::Reader::open(config.output);
  const auto dims = reader.dims();
  EXPECT_EQ(dims[0], 256);
  EXPECT_EQ(dims[1], 192);
  EXPECT_EQ(dims[2], kSlices);
  const int nx = int(dims[0]), ny = int(dims[1]), nz = int(dims[2]);
  const std::size_t plane = std::size_t(nx) * ny, n = plane * nz;
  std::vector<std::uint8_t> rgba(n * 4);
  std::vector<std::int16_t> ct(n);
  std::vector<std::uint8_t> labels(n);
  reader.read_region("rgba", 0, 0, 0, 0, nx, ny, nz, rgba.data());
  reader.read_region("ct", 0, 0, 0, 0, nx, ny, nz, ct.data());
  const int label_channel = reader.channel_index("labels");
  EXPECT_EQ(reader.channels()[label_channel].type, format::ChannelType::kUint8);  // IDs <= 9
  reader.read_region(label_channel, 0, 0, 0, 0, nx, ny, nz, labels.data());

  NrrdVolume t_rgb = read_nrrd(dir / "truth/rgb.nrrd"), t_ct = read_nrrd(dir / "truth/ct.nrrd"),
             t_mask = read_nrrd(dir / "truth/mask.nrrd"),
             t_lab = read_nrrd(dir / "truth/labels.nrrd");
  const StackTransforms truth_t = read_transforms(dir / "truth/transforms.json");
  const auto truth_json = nlohmann::json::parse(read_file(dir / "truth/transforms.json"));
  const double ct_scale = truth_json["ct_to_rgb"]["scale"];  // CT pixel / RGB pixel (2.73)

  PackedVsTruth r;
  int compared_slices = 0;
  for (int z = 0; z < nz; ++z) {
    // A black slice carries no colour, and its labels (a black seg) are 0; a duplicated slice
    // shows the previous slice's anatomy. Neither can agree with truth; the packed metadata
    // lists both (test_pack).
    if (truth_t.slices[z].black || truth_t.slices[z].duplicate_of) continue;
    ++compared_slices;
    const double gain = truth_json["slices"][z]["gain"];
    cv::Mat lab(ny, nx, CV_16UC1, t_lab.as<std::uint16_t>() + plane * z);
    cv::Mat tct(ny, nx, CV_16SC1, t_ct.as<std::int16_t>() + plane * z);
    const cv::Mat inner = uniform_within(lab, 1);
    // "Flat" CT: the truth HU varies by < 50 within +-2 CT pixels (a CT sample there sees one
    // tissue; the model's texture varies by tens of HU inside a tissue).
    const int ct_r = int(std::ceil(2 * ct_scale));
    cv::Mat ctf, lo, hi;
    tct.convertTo(ctf, CV_32F);
    const cv::Mat k =
        cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * ct_r + 1, 2 * ct_r + 1));
    cv::erode(ctf, lo, k, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
    cv::dilate(ctf, hi, k, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
    const cv::Mat flat = (hi - lo) < 50;
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x) {
        const std::size_t i = plane * z + std::size_t(y) * nx + x;
        const bool a = rgba[i * 4 + 3] >= 128, b = t_mask.as<std::uint8_t>()[i] != 0;
        r.inter += a && b;
        r.uni += a || b;
        if (!b) continue;
        const bool in = inner.at<std::uint8_t>(y, x) != 0;
        for (int c = 0; c < 3; ++c) {
          // The observed slice is gain_k * model + noise; the gain is a property of the photo,
          // which the pipeline keeps (it does not normalise brightness): divide it out.
          double e = std::abs(rgba[i * 4 + c] / gain - double(t_rgb.as<std::uint8_t>()[i * 3 + c]));
          r.rgb_abs += e;
          ++r.rgb_n;
          if (in) r.rgb_abs_inner += e, ++r.rgb_n_inner;
        }
        const double ce = std::abs(int(ct[i]) - int(t_ct.as<std::int16_t>()[i]));
        r.ct_abs += ce;
        ++r.ct_n;
        if (flat.at<std::uint8_t>(y, x)) r.ct_abs_flat += ce, ++r.ct_n_flat;
        const bool eq = labels[i] == t_lab.as<std::uint16_t>()[i];
        ++r.lab_body;
        r.lab_body_eq += eq;
        if (in) ++r.lab_inner, r.lab_inner_wrong += !eq;
      }
  }
  EXPECT_EQ(compared_slices, kSlices - 2);  // the defects: one black, one duplicated slice
  r.finish();
  std::printf(
      "%s: pack vs truth (small, %d slices): alpha IoU %.4f; colour MAE %.2f (%.2f away from "
      "edges); "
      "CT MAE %.1f HU in body (%.1f HU where flat); labels %.4f in body, %.5f wrong away from "
      "edges (%llu of %llu)\n",
      what.c_str(), kSlices, r.iou(), r.rgb_mae, r.rgb_mae_inner, r.ct_mae, r.ct_mae_flat,
      r.lab_body_fraction, r.lab_inner_wrong_fraction, (unsigned long long)r.lab_inner_wrong,
      (unsigned long long)r.lab_inner);

  return r;
}

// The tolerances, shared by both tests below.
void expect_within_tolerances(const PackedVsTruth& r, bool check_alpha) {
  ASSERT_GT(r.rgb_n_inner, 3u * 150000u);  // (pixels x 3 channels) away from label edges
  ASSERT_GT(r.ct_n_flat, 50000u);          // body pixels where the CT is flat
  // Alpha: the mask goal, IoU >= 0.99 against truth/mask.nrrd.
  if (check_alpha) {
    EXPECT_GE(r.iou(), 0.99);
  }
  // Colour away from label edges (truth 3x3 uniform), gain divided out: what is left is the
  // phantom's sensor noise (sigma 3 levels: mean |noise| = 3 * sqrt(2/pi) = 2.4; bilinear
  // resampling averages neighbours and only lowers it), the tissue texture moved by the residual
  // drift (<= 0.1 px times a texture gradient of a few levels per px: < 0.5) and 8-bit rounding
  // (0.25): <= 3.0.
  EXPECT_LE(r.rgb_mae_inner, 3.0);
  // Colour over the whole truth mask adds the label edges, where a drift error of 0.1 px moves
  // a colour step (up to ~150 levels between tissues, blurred over 1 px by the model) by 0.1 px:
  // ~15 levels on the ~10 % of body pixels next to an edge = 1.5 more: <= 4.5.
  EXPECT_LE(r.rgb_mae, 4.5);
  // CT where the truth HU is flat over +-2 CT pixels: the CT sample sees one tissue, so only the
  // CT noise (6 HU, 0.8 * 6 = 4.8 mean absolute, lowered by interpolation) and the texture
  // (< 50 HU range by selection, averaged over a CT pixel) remain: <= 10 HU.
  EXPECT_LE(r.ct_mae_flat, 10.0);
  // CT over the whole body: a CT pixel is 2.7 RGB pixels wide (0.9 vs 0.33 mm) and the scanner
  // model blurs every tissue edge over one CT pixel, so interpolating the CT onto the colour grid
  // smears each edge (bone/soft tissue ~1000 HU, lung/soft tissue ~800 HU, body/air) over ~3 RGB
  // pixels; that cannot be undone. Its size: 47.3 HU measured when every stage gets the TRUE
  // transforms (PackTruth.TrueTransformsChannelsAgreeWithTruth, seed 3), against 7.3 HU where the
  // CT is flat. Tolerance: that floor + 15 % for the CT->RGB alignment and mask edge at their
  // goals: <= 55 HU.
  EXPECT_LE(r.ct_mae, 55.0);
  // Labels away from edges (truth 3x3 uniform): nearest-neighbour resampling moves a sample by
  // <= 0.71 px, registration error by <= 0.1 px more, so a pixel >= 1 px from every boundary keeps
  // its label: at most 0.1 % wrong (thin slivers between samples; measured 1 of 212,190). Whole
  // body: the half-pixel nearest-neighbour loss along every edge (97.0 % measured with the TRUE
  // transforms, seed 3; see test_labels SegTruth.ResampledLabelsExactAwayFromEdges) less 1 point
  // for a drift error of 0.1 px on the ~10 % of body pixels next to an edge: >= 96 %.
  EXPECT_LE(r.lab_inner_wrong_fraction, 0.001);
  EXPECT_GE(r.lab_body_fraction, 0.96);
}

}  // namespace

// The whole pipeline as a user runs it (register, mask, labels, pack).
TEST(PackTruth, PipelineChannelsAgreeWithTruth) {
  test::TempDir dir;
  Config config = make_small_phantom(dir);
  RunOptions options;
  options.quiet = true;
  options.to = "pack";
  run_pipeline(config, options);
  expect_within_tolerances(compare_packed_with_truth(dir, config, "pipeline"), true);
}

// The same tolerances met by the pack stage fed with the TRUE transforms: the registered slices
// are the observed ones warped with truth/transforms.json exactly as vispack-register warps them
// (bilinear, border replicated), then the mask, labels and pack stages run as usual. This shows
// the tolerances are reachable once registration meets its goal, and isolates registration error
// from the rest. Alpha is not asserted here: it is the mask stage's own result (the mask goal is
// asserted in the test above).
TEST(PackTruth, TrueTransformsChannelsAgreeWithTruth) {
  test::TempDir dir;
  Config config = make_small_phantom(dir);
  make_directories(config.work_dir + "/register/registered");
  std::filesystem::copy_file(dir / "truth/transforms.json", transforms_path(config));
  const StackTransforms t = read_transforms(transforms_path(config));
  const std::vector<SliceFile> stack = stack_slices(config);
  ASSERT_EQ(int(stack.size()), kSlices);
  for (int k = 0; k < kSlices; ++k) {
    cv::Mat observed = read_slice(stack[std::size_t(k)].path, config.rgb.raw), registered;
    cv::warpAffine(observed, registered, cv::Mat(rigid_matrix(t.slices[k].rigid, grid_centre(t))),
                   observed.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
    write_image(registered_rgb_path(config, k), registered);
  }
  RunOptions options;
  options.quiet = true;
  options.from = "mask";
  options.to = "pack";
  run_pipeline(config, options);
  expect_within_tolerances(compare_packed_with_truth(dir, config, "true transforms"), false);
}

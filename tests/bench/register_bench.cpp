// Registration throughput at the Visible Human size (2048×1216), on 1 and 2 threads: time per
// slice pair (frame preparation + phase correlation + ECC at ecc_scale) with the error against a
// known synthetic motion, and time per slice of the stage's work on a drifting stack (each
// slice prepared once and registered against its two predecessors, compute_pairs) with the
// chained error. Wall and CPU time. Prints tables (docs/BENCHMARKS.md "Registration anchored on the
// CT").
//   build/bin/register_bench [--slices N]
// The CT-anchored stack (docs/BENCHMARKS.md, 'Registration anchored on the CT'): the same stack
// against a CT 2.84× coarser, every slice prepared once, registered against two predecessors and
// anchored on its CT slice, then solved. Phantom mode (scripts/bench.sh): registers consecutive
// slice pairs of a vispack-phantom folder with every method and ecc_scale offered, one thread, and
// writes the estimated and true pair matrices as JSON (errors are computed by the caller, the same
// way for every peer); --dump also writes each pair's grey slices as MetaImage (.mhd + .raw) for
// elastix. Each repetition times the estimate in memory (frames already decoded) and, apart,
// reading both slices from their PNG files as the stage does (elastix reads its two files too: the
// comparison adds them).
//   build/bin/register_bench --phantom DIR [--pairs N] [--reps R] --json OUT [--dump DIR]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"

#include "vispack/common/parallel.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/register/register.h"

namespace vp = vispack::pipeline;

namespace {

// A VHP-sized textured body in gel (smooth multi-scale texture).
cv::Mat synthetic_slice(cv::Size size) {
  std::mt19937 rng(42);
  std::normal_distribution<float> noise(0.f, 1.f);
  cv::Mat acc(size, CV_32FC3, cv::Scalar::all(0));
  for (int octave : {64, 16, 4}) {
    cv::Mat small(size.height / octave + 2, size.width / octave + 2, CV_32FC3);
    for (int y = 0; y < small.rows; ++y)
      for (int x = 0; x < small.cols; ++x)
        small.at<cv::Vec3f>(y, x) = {noise(rng), noise(rng), noise(rng)};
    cv::Mat up;
    cv::resize(small, up, size, 0, 0, cv::INTER_CUBIC);
    acc += up;
  }
  cv::normalize(acc, acc, 30, 230, cv::NORM_MINMAX);
  cv::Mat body(size, CV_8U, cv::Scalar(0));
  cv::ellipse(body, {size.width / 2, size.height / 2}, {size.width * 2 / 5, size.height * 2 / 5}, 0,
              0, 360, cv::Scalar(255), -1);
  cv::Mat out(size, CV_8UC3, cv::Scalar(40, 70, 160)), tex;
  acc.convertTo(tex, CV_8UC3);
  tex.copyTo(out, body);
  return out;
}

nlohmann::json matrix_json(const cv::Matx23d& m) {
  return {{m(0, 0), m(0, 1), m(0, 2)}, {m(1, 0), m(1, 1), m(1, 2)}};
}

// Writes a grey CV_8U image as MetaImage (header .mhd + raw .raw beside it), spacing 1, origin 0,
// so that elastix's physical coordinates are OpenCV's pixel coordinates.
void write_mhd(const std::string& stem, const cv::Mat& grey) {
  const std::string raw_name = stem.substr(stem.find_last_of('/') + 1) + ".raw";
  vispack::write_file_atomic(stem + ".raw", grey.data, grey.total());
  vispack::write_file_atomic(
      stem + ".mhd",
      "ObjectType = Image\nNDims = 2\nBinaryData = True\nBinaryDataByteOrderMSB = "
      "False\nElementSpacing = 1 1\nOffset = 0 0\nDimSize = " +
          std::to_string(grey.cols) + " " + std::to_string(grey.rows) +
          "\nElementType = MET_UCHAR\nElementDataFile = " + raw_name + "\n");
}

// Phantom mode: see the top of the file.
int run_phantom(const std::string& dir, int max_pairs, int reps, const std::string& json_out,
                const std::string& dump) {
  std::ifstream in(dir + "/truth/transforms.json");
  if (!in) throw vispack::IoError(dir + "/truth/transforms.json: cannot open");
  const nlohmann::json truth = nlohmann::json::parse(in);
  const auto& slices = truth.at("slices");
  auto usable = [&](std::size_t k) {
    const auto& s = slices[k];
    return !s.at("black").get<bool>() && s.at("duplicate_of").is_null() &&
           !s.at("jump").get<bool>();
  };
  auto path_of = [&](std::size_t k) {
    return dir + "/rgb/" + slices[k].at("file").get<std::string>();
  };
  auto load = [&](std::size_t k) {
    const std::string path = path_of(k);
    cv::Mat m = cv::imread(path, cv::IMREAD_COLOR);
    if (m.empty()) throw vispack::IoError(path + ": cannot read");
    cv::cvtColor(m, m, cv::COLOR_BGR2RGB);  // the pipeline's slices are RGB
    return m;
  };
  auto rigid = [&](std::size_t k) {
    const auto& s = slices[k];
    return vp::Rigid{s.at("rotation_deg").get<double>(), s.at("dx_px").get<double>(),
                     s.at("dy_px").get<double>()};
  };
  // Consecutive usable pairs (k-1, k), neither end black, duplicated or a jump.
  std::vector<std::pair<std::size_t, std::size_t>> pairs;
  for (std::size_t k = 1; k < slices.size() && int(pairs.size()) < max_pairs; ++k)
    if (usable(k) && usable(k - 1)) pairs.emplace_back(k - 1, k);
  if (pairs.empty()) throw vispack::InputError(dir + ": no usable consecutive slice pair");
  std::vector<cv::Mat> from, to;
  nlohmann::json out;
  out["phantom"] = dir;
  nlohmann::json jp = nlohmann::json::array();
  for (std::size_t i = 0; i < pairs.size(); ++i) {
    from.push_back(load(pairs[i].first));
    to.push_back(load(pairs[i].second));
    const cv::Point2d c = vp::image_centre(from.back().size());
    // Truth: T_k = relative ∘ T_j, so relative = T_k ∘ T_j^-1 (observed j -> observed k).
    const cv::Matx23d rel =
        vp::compose_affine(vp::rigid_matrix(rigid(pairs[i].second), c),
                           vp::invert_affine(vp::rigid_matrix(rigid(pairs[i].first), c)));
    jp.push_back({{"from", pairs[i].first}, {"to", pairs[i].second}, {"truth", matrix_json(rel)}});
    if (!dump.empty()) {
      cv::Mat g;
      cv::cvtColor(from.back(), g, cv::COLOR_RGB2GRAY);
      write_mhd(dump + "/pair" + std::to_string(i) + "_fixed", g);
      cv::cvtColor(to.back(), g, cv::COLOR_RGB2GRAY);
      write_mhd(dump + "/pair" + std::to_string(i) + "_moving", g);
    }
  }
  out["width"] = from[0].cols;
  out["height"] = from[0].rows;
  out["pairs"] = jp;
  nlohmann::json results = nlohmann::json::array();
  struct Setting {
    const char* method;
    double ecc_scale;
  };
  cv::setNumThreads(1);
  for (Setting st : {Setting{"phase", 0.5}, Setting{"phase+ecc", 0.125}, Setting{"phase+ecc", 0.25},
                     Setting{"phase+ecc", 0.5}, Setting{"phase+ecc", 1.0}}) {
    vp::RegisterOptions options;
    options.method = st.method;
    options.ecc_scale = st.ecc_scale;
    nlohmann::json mats = nlohmann::json::array();
    std::vector<double> times, cpu, read_times, read_cpu;
    for (int r = 0; r < reps; ++r) {
      // Reading both slices of every pair from their files (decode + RGB order), timed apart.
      {
        const std::clock_t c0 = std::clock();
        const auto t0 = std::chrono::steady_clock::now();
        for (std::size_t i = 0; i < pairs.size(); ++i) {
          cv::Mat a = load(pairs[i].first), b = load(pairs[i].second);
          if (a.size() != from[i].size() || b.size() != to[i].size())
            throw vispack::IoError(path_of(pairs[i].first) + ": size changed");
        }
        read_times.push_back(
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() /
            double(pairs.size()));
        read_cpu.push_back(double(std::clock() - c0) / CLOCKS_PER_SEC / double(pairs.size()));
      }
      // Per pair: both frames prepared and the pair estimated (elastix also reads both images).
      const std::clock_t c0 = std::clock();  // process CPU time: steadier on a loaded machine
      const auto t0 = std::chrono::steady_clock::now();
      std::vector<vp::PairEstimate> est;
      for (std::size_t i = 0; i < pairs.size(); ++i)
        est.push_back(vp::estimate_pair(vp::prepare_frame(from[i], options),
                                        vp::prepare_frame(to[i], options), options));
      times.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() /
                      double(pairs.size()));
      cpu.push_back(double(std::clock() - c0) / CLOCKS_PER_SEC / double(pairs.size()));
      if (r == 0)
        for (std::size_t i = 0; i < est.size(); ++i)
          mats.push_back(
              matrix_json(vp::rigid_matrix(est[i].relative, vp::image_centre(from[i].size()))));
    }
    auto med = [](std::vector<double> v) {
      std::sort(v.begin(), v.end());
      return v[v.size() / 2];
    };
    results.push_back({{"method", st.method},
                       {"cpu_seconds_per_pair", med(cpu)},
                       {"ecc_scale", std::string(st.method) == "phase" ? 0.0 : st.ecc_scale},
                       {"seconds_per_pair", med(times)},
                       {"read_seconds_per_pair", med(read_times)},
                       {"read_cpu_seconds_per_pair", med(read_cpu)},
                       {"times", times},
                       {"cpu_times", cpu},
                       {"read_times", read_times},
                       {"read_cpu_times", read_cpu},
                       {"estimates", mats}});
    std::fprintf(stderr, "register_bench: %s ecc_scale %.3g: %.1f ms/pair (+ %.1f ms reading)\n",
                 st.method, st.ecc_scale, 1e3 * med(times), 1e3 * med(read_times));
  }
  out["results"] = results;
  vispack::write_file_atomic(json_out, out.dump(1));
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  std::string phantom, json_out, dump;
  int max_pairs = 4, reps = 3;
  for (int i = 1; i + 1 < argc; ++i) {
    if (!std::strcmp(argv[i], "--phantom")) phantom = argv[i + 1];
    if (!std::strcmp(argv[i], "--json")) json_out = argv[i + 1];
    if (!std::strcmp(argv[i], "--dump")) dump = argv[i + 1];
    if (!std::strcmp(argv[i], "--pairs")) max_pairs = std::max(1, std::atoi(argv[i + 1]));
    if (!std::strcmp(argv[i], "--reps")) reps = std::max(1, std::atoi(argv[i + 1]));
  }
  if (!phantom.empty()) {
    if (json_out.empty()) {
      std::fprintf(stderr, "register_bench: --phantom needs --json OUT\n");
      return 2;
    }
    try {
      return run_phantom(phantom, max_pairs, reps, json_out, dump);
    } catch (const std::exception& e) {
      std::fprintf(stderr, "register_bench: %s\n", e.what());
      return 1;
    }
  }
  int pairs = 8;
  for (int i = 1; i + 1 < argc; ++i)
    if (!std::strcmp(argv[i], "--slices")) pairs = std::max(2, std::atoi(argv[i + 1]));
  const cv::Size size(2048, 1216);
  const cv::Mat base = synthetic_slice(size);
  // Slice k is the base moved by a known drift (sub-pixel shift and small rotation).
  std::vector<vp::Rigid> truth(std::size_t(pairs) + 1);
  std::vector<cv::Mat> slices(truth.size());
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (std::size_t k = 0; k < truth.size(); ++k) {
    truth[k] = k == 0 ? vp::Rigid{} : vp::Rigid{0.3 * u(rng), 3.0 * u(rng), 3.0 * u(rng)};
    cv::warpAffine(base, slices[k], cv::Mat(vp::rigid_matrix(truth[k], vp::image_centre(size))),
                   size, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  }
  vp::RegisterOptions options;
  // 1. Pairs: each slice k >= 1 against slice 0 (the relative motion is truth[k]).
  std::printf(
      "| threads | method | ms/pair (prepare + pair), wall | CPU ms/pair | RMS error px | "
      "max error px |\n");
  std::printf("|---|---|---|---|---|---|\n");
  for (const char* method : {"phase", "phase+ecc"}) {
    for (int threads : {1, 2}) {
      cv::setNumThreads(1);
      options.method = method;
      const std::clock_t c0 = std::clock();  // process CPU time, all threads
      const auto t0 = std::chrono::steady_clock::now();
      std::vector<vp::RegisterFrame> frames(truth.size());
      std::vector<vp::PairEstimate> est(static_cast<std::size_t>(pairs));
      vispack::parallel_for(std::int64_t(truth.size()), threads, [&](std::int64_t k) {
        frames[std::size_t(k)] = vp::prepare_frame(slices[std::size_t(k)], options);
      });
      vispack::parallel_for(pairs, threads, [&](std::int64_t i) {
        est[std::size_t(i)] = vp::estimate_pair(frames[0], frames[std::size_t(i) + 1], options);
      });
      const double seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      const double cpu = double(std::clock() - c0) / CLOCKS_PER_SEC;
      double sum2 = 0, worst = 0;
      for (int i = 0; i < pairs; ++i) {
        const auto& r = est[std::size_t(i)].relative;
        const auto& t = truth[std::size_t(i) + 1];
        // Error as the largest corner displacement of the residual transform.
        vp::Rigid diff{r.rotation_deg - t.rotation_deg, r.dx_px - t.dx_px, r.dy_px - t.dy_px};
        const double e = vp::rigid_motion_px(diff, size);
        sum2 += e * e;
        worst = std::max(worst, e);
      }
      std::printf("| %d | %s | %.1f | %.1f | %.3f | %.3f |\n", threads, method,
                  1000.0 * seconds / pairs, 1000.0 * cpu / pairs, std::sqrt(sum2 / pairs), worst);
    }
  }
  // 2. The stage's work per slice: a drifting stack (random walk, σ 0.3 px and 0.05° per
  //    slice) with two fiducial tubes in the gel, every slice prepared once and registered
  //    against its two predecessors (compute_pairs), then chained (chain_transforms).
  const int n = pairs + 1;
  std::vector<vp::Rigid> walk(static_cast<std::size_t>(n));
  std::vector<cv::Mat> stack(static_cast<std::size_t>(n));
  cv::Mat tubes = base.clone();
  cv::circle(tubes, {150, 150}, 45, cv::Scalar(72, 176, 84), -1, cv::LINE_AA);
  cv::circle(tubes, {size.width - 150, size.height - 150}, 45, cv::Scalar(72, 176, 84), -1,
             cv::LINE_AA);
  std::normal_distribution<double> step(0.0, 1.0);
  for (int k = 0; k < n; ++k) {
    if (k > 0)
      walk[std::size_t(k)] = {walk[std::size_t(k) - 1].rotation_deg + 0.05 * step(rng),
                              walk[std::size_t(k) - 1].dx_px + 0.3 * step(rng),
                              walk[std::size_t(k) - 1].dy_px + 0.3 * step(rng)};
    cv::warpAffine(tubes, stack[std::size_t(k)],
                   cv::Mat(vp::rigid_matrix(walk[std::size_t(k)], vp::image_centre(size))), size,
                   cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  }
  std::printf(
      "\n| threads | stack of %d slices, phase+ecc | ms/slice (prepare + 2 pairs), wall | "
      "CPU ms/slice | chained RMS error px (centre) |\n",
      n);
  std::printf("|---|---|---|---|---|\n");
  options.method = "phase+ecc";
  for (int threads : {1, 2}) {
    cv::setNumThreads(1);
    const std::clock_t c0 = std::clock();
    const auto t0 = std::chrono::steady_clock::now();
    const std::vector<vp::SlicePairs> records = vp::compute_pairs(
        0, n, [&](int k) { return vp::prepare_frame(stack[std::size_t(k)], options); }, options,
        threads);
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const double cpu = double(std::clock() - c0) / CLOCKS_PER_SEC;
    const auto chained = vp::chain_transforms(records, size, options.jump_px);
    double sum2 = 0;
    for (int k = 0; k < n; ++k) {
      const auto& t = chained[std::size_t(k)];
      const auto& w = walk[std::size_t(k)];
      sum2 += std::pow(t.rigid.dx_px - w.dx_px, 2) + std::pow(t.rigid.dy_px - w.dy_px, 2);
    }
    std::printf("| %d | compute_pairs | %.1f | %.1f | %.3f |\n", threads, 1000.0 * seconds / n,
                1000.0 * cpu / n, std::sqrt(sum2 / n));
  }
  // 3. With the CT anchor: the same drifting stack against a CT 2.84× coarser
  //    (VHP: 0.9375 mm CT, 0.33 mm colour) rendered from the undrifted body in the CT-defined
  //    frame (HU from the grey level inside the body, −1000 outside). Per slice: the frame
  //    prepared once (with its anchor level), the two pair edges and the anchor (compute_pairs
  //    with the anchor callback), then the global solve; error against the walk at the corners
  //    and centre.
  {
    const vp::Similarity frame{0.9375 / 0.33, 0.0, 0.0, 0.0};
    const cv::Size ct_size(int(std::lround(size.width / frame.scale)),
                           int(std::lround(size.height / frame.scale)));
    cv::Mat grey, body_mask(size, CV_8U, cv::Scalar(0)), hu;
    cv::cvtColor(tubes, grey, cv::COLOR_RGB2GRAY);
    cv::ellipse(body_mask, {size.width / 2, size.height / 2},
                {size.width * 2 / 5, size.height * 2 / 5}, 0, 0, 360, cv::Scalar(255), -1);
    grey.convertTo(hu, CV_32F, 6.0, -700.0);
    hu.setTo(cv::Scalar(-1000.0), body_mask == 0);
    cv::Mat ct;
    cv::resize(hu, ct, ct_size, 0, 0, cv::INTER_AREA);
    const double anchor_scale = 1.0 / frame.scale;
    std::printf(
        "\n| threads | stack of %d slices, phase+ecc + CT anchor (CT %.2fx coarser) | ms/slice "
        "(prepare + 2 pairs + anchor), wall | CPU ms/slice | of which anchor, CPU ms | solved "
        "RMS error px (corners and centre) |\n",
        n, frame.scale);
    std::printf("|---|---|---|---|---|---|\n");
    for (int threads : {1, 2}) {
      cv::setNumThreads(1);
      std::clock_t anchor_cpu = 0;
      const std::clock_t c0 = std::clock();
      const auto t0 = std::chrono::steady_clock::now();
      const std::vector<vp::SlicePairs> records = vp::compute_pairs(
          0, n,
          [&](int k) { return vp::prepare_frame(stack[std::size_t(k)], options, anchor_scale); },
          options, threads,
          [&](int, const vp::RegisterFrame& f) -> std::optional<vp::AnchorEstimate> {
            const std::clock_t a0 = std::clock();
            vp::AnchorEstimate a = vp::estimate_ct_anchor(f, ct, frame, {});
            if (threads == 1) anchor_cpu += std::clock() - a0;
            return a;
          });
      vp::StackSolveOptions so;
      so.anchor = "ct";
      const vp::StackSolve solved = vp::solve_stack(records, size, so);
      const double seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      const double cpu = double(std::clock() - c0) / CLOCKS_PER_SEC;
      double sum2 = 0;
      for (int k = 0; k < n; ++k) {
        const cv::Point2d c = vp::image_centre(size);
        const vp::Rigid d = vp::rigid_from_matrix(
            vp::compose_affine(vp::rigid_matrix(solved.slices[std::size_t(k)].rigid, c),
                               vp::invert_affine(vp::rigid_matrix(walk[std::size_t(k)], c))),
            c);
        sum2 += std::pow(vp::rigid_motion_px(d, size), 2);
      }
      std::printf(
          "| %d | compute_pairs + anchors + solve_stack | %.1f | %.1f | %s | %.3f |\n", threads,
          1000.0 * seconds / n, 1000.0 * cpu / n,
          threads == 1
              ? std::to_string(int(std::lround(1000.0 * double(anchor_cpu) / CLOCKS_PER_SEC / n)))
                    .c_str()
              : "-",
          std::sqrt(sum2 / n));
    }
  }
  std::printf(
      "(wall: elapsed time, inflated by other processes on a loaded machine; CPU: process\n"
      " CPU time of all threads)\n");
  return 0;
}

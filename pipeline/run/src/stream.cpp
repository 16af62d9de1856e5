#include "vispack/pipeline/run/stream.h"

#include <condition_variable>
#include <exception>
#include <map>
#include <memory>
#include <mutex>

#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/pipeline/core/work_layout.h"
#include "vispack/pipeline/imaging/intermediates.h"
#include "vispack/pipeline/imaging/opencv_threads.h"
#include "vispack/pipeline/imaging/transforms.h"
#include "vispack/pipeline/labels/labels_stage.h"
#include "vispack/pipeline/mask/mask_stage.h"
#include "vispack/pipeline/pack/pack.h"

namespace vispack::pipeline {

namespace {

using SlicePtr = PackStream::SlicePtr;

// Runs produce(k) for k in [0, n) on `threads` workers and consume(k, result) in k order, at
// most `window` slices claimed and not yet consumed. The worker that completes the next slice in
// order consumes it (and any later ones ready), so one thread runs the whole thing serially. The
// first exception stops the claiming of new slices and is rethrown after every worker returned.
void ordered_pipeline(int n, int threads, int window, const std::function<SlicePtr(int)>& produce,
                      const std::function<void(int, SlicePtr)>& consume) {
  std::mutex mutex;
  std::condition_variable cv;
  int next_claim = 0, next_consume = 0;
  bool consuming = false;
  std::exception_ptr error;
  std::map<int, SlicePtr> ready;
  parallel_for(threads, threads, [&](std::int64_t) {
    for (;;) {
      int k = 0;
      {
        std::unique_lock<std::mutex> lock(mutex);
        cv.wait(lock,
                [&] { return error || next_claim >= n || next_claim < next_consume + window; });
        if (error || next_claim >= n) return;
        k = next_claim++;
      }
      try {
        SlicePtr result = produce(k);
        std::unique_lock<std::mutex> lock(mutex);
        ready.emplace(k, std::move(result));
        if (consuming) continue;
        consuming = true;
        while (!error && !ready.empty() && ready.begin()->first == next_consume) {
          SlicePtr next = std::move(ready.begin()->second);
          ready.erase(ready.begin());
          lock.unlock();
          try {
            consume(next_consume, std::move(next));
          } catch (...) {
            lock.lock();
            consuming = false;
            throw;
          }
          lock.lock();
          ++next_consume;
          cv.notify_all();
        }
        consuming = false;
      } catch (...) {
        std::lock_guard<std::mutex> lock(mutex);
        if (!error) error = std::current_exception();
        cv.notify_all();
        return;
      }
    }
  });
  if (error) std::rethrow_exception(error);
}

}  // namespace

std::vector<StageResult> run_stream(const Config& config, const StageOptions& options) {
  const StackInputs inputs = read_stack_inputs(config);
  const cv::Size size = grid_size(inputs.transforms);
  MaskStageJob mask(config, inputs, options);
  const SliceRange range = mask.run().range();  // options.slices, or the whole stack
  std::unique_ptr<LabelsStageJob> labels;
  if (config.seg) labels = std::make_unique<LabelsStageJob>(config, options);
  const int threads = mask.run().threads();
  ScopedOpenCvThreads opencv_threads(1);
  // The slices in flight (2 per thread) and the CT slices beside them.
  CtHuCache ct_cache(std::size_t(4 * threads + 4));

  // What is up to date, decided before anything is written (index i = slice range.first + i).
  const int count = range.size();
  std::vector<char> mask_fresh(std::size_t(count), 0), labels_fresh(std::size_t(count), 1);
  bool all_fresh = true;
  for (int i = 0; i < count; ++i) {
    mask_fresh[std::size_t(i)] = mask.up_to_date(range.first + i);
    if (labels) labels_fresh[std::size_t(i)] = labels->up_to_date(range.first + i);
    all_fresh = all_fresh && mask_fresh[std::size_t(i)] && labels_fresh[std::size_t(i)];
  }
  std::unique_ptr<PackStream> pack;
  if (!all_fresh && PackStream::streamable(config, inputs.rgb, range))
    pack = std::make_unique<PackStream>(config, options);

  // Slice k: read once, computed once, written as the stages write it, converted for the pack.
  auto produce = [&](int i) -> SlicePtr {
    const int k = range.first + i;
    const bool mask_done = mask_fresh[std::size_t(i)], labels_done = labels_fresh[std::size_t(i)];
    Intermediates in;
    if (mask_done) {
      mask.skip(k);
      if (pack) {
        in.rgb = registered_colour(config, inputs, k);
        in.mask = read_checked(mask_path(config, k), CV_8UC1, size);
        if (config.ct) in.ct = resampled_ct16(config, inputs, k, nullptr, &ct_cache);
      }
    } else {
      in.rgb = registered_colour(config, inputs, k);
      const CtSlice ct = read_ct_slice(config, inputs, k, /*for_mask=*/true, &ct_cache);
      in.mask = mask.compute(k, in.rgb, ct, pack && config.ct ? &in.ct : nullptr);
    }
    if (labels) {
      if (!labels_done) {
        in.labels = labels->compute(k);
      } else {
        labels->skip(k);
        if (pack) in.labels = read_checked(labels_path(config, k), CV_16UC1, size);
      }
    }
    if (!pack) return nullptr;
    in.bytes = in.rgb.total() * 3 + in.mask.total() + in.ct.total() * 2 + in.labels.total() * 2;
    clear_outside_body(config, in);
    return pack->convert(std::move(in));
  };
  auto consume = [&](int, SlicePtr slice) {
    if (pack) pack->append(std::move(slice));
  };
  try {
    ordered_pipeline(count, std::max(1, std::min(threads, count)), 2 * threads, produce, consume);
  } catch (...) {
    // The slices finished before the error stay recorded: a rerun resumes after them.
    mask.run().flush();
    if (labels) labels->run().flush();
    throw;
  }

  std::vector<StageResult> results;
  results.push_back(mask.finish());
  if (labels) results.push_back(labels->finish());
  results.push_back(pack ? pack->finish() : run_pack_stage(config, options));
  return results;
}

}  // namespace vispack::pipeline

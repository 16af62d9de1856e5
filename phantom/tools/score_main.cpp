// vispack-score: scores a pipeline work folder against a phantom's truth (score.h).
#include <cmath>
#include <cstdio>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/phantom/score.h"

int main(int argc, char** argv) {
  return vispack::run_main("vispack-score", argc, argv, [](vispack::Args& args) {
    args.describe(
        "--truth DIR --work DIR [--json]",
        "Scores a pipeline work folder (register/transforms.json, mask/, labels/) against\n"
        "a phantom's truth folder: drift error per slice (largest displacement of the\n"
        "corners and centre, px; and over the truth body, where the error shows), jumps\n"
        "found/false, mask IoU, labels away from edges.");
    const auto truth = args.option("--truth", "DIR", "the phantom's truth/ folder");
    const auto work = args.option("--work", "DIR", "the pipeline's work folder (config work_dir)");
    const bool as_json = args.flag("--json", "print the full score as JSON");
    args.done();
    if (!truth || !work) throw vispack::UsageError("--truth DIR and --work DIR are required");
    const auto s = vispack::phantom::score_work(*truth, *work);
    if (as_json) {
      std::printf("%s\n", vispack::phantom::to_json(s).dump(2).c_str());
      return 0;
    }
    std::printf("frames: truth \"%s\", estimate \"%s\"%s\n", s.truth_frame.c_str(),
                s.estimate_frame.c_str(),
                s.truth_frame != s.estimate_frame
                    ? " (they differ: absolute errors include the offset between the frames)"
                    : "");
    std::printf(
        "drift: rms %.3f px, max %.3f px (slice %d) over %d slices; relative to slice 0: "
        "rms %.3f px, max %.3f px\n",
        s.drift.rms_px, s.drift.max_px, s.drift.max_slice, s.drift.scored, s.drift.relative_rms_px,
        s.drift.relative_max_px);
    std::printf("drift over the %d slices with body >= 1 %%: rms %.3f px, max %.3f px\n",
                s.drift.body_slices, s.drift.body_rms_px, s.drift.body_max_px);
    std::printf(
        "drift over the truth body (%d slices with body): rms %.3f px, max %.3f px (slice %d)\n",
        s.drift.over_body_slices, s.drift.over_body_rms_px, s.drift.over_body_max_px,
        s.drift.over_body_max_slice);
    std::printf("jumps: %d of %d found, %d false\n", s.jumps.found, s.jumps.true_jumps,
                s.jumps.false_jumps);
    if (s.has_mask)
      std::printf(
          "mask: stack IoU %.4f; slices with body >= 1 %%: %d, mean IoU %.4f, min %.4f "
          "(slice %d)\n",
          s.mask.stack_iou, s.mask.body_slices, s.mask.mean_body_iou, s.mask.min_body_iou,
          s.mask.min_body_slice);
    if (s.has_labels)
      std::printf(
          "labels: %.4f equal away from class edges (%llu px, %d slices), worst %.4f "
          "(slice %d)\n",
          s.labels.overall, static_cast<unsigned long long>(s.labels.counted),
          s.labels.scored_slices, s.labels.worst, s.labels.worst_slice);
    return 0;
  });
}

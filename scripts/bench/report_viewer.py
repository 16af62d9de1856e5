"""The viewer against VTK's GPU ray caster.
A section mixin of report.py's Report: self.w, self.save, self.res and the rest come from it."""
import math
import os


from report_common import OURS, PEER, fmt, load, plain_ticks, plt, table  # noqa: E402


class ViewerSection:
    @staticmethod
    def _ms_at_psnr(rows, q):
        """Frame time at foreground PSNR q along a renderer's time-vs-PSNR curve (its rows, one per
        sampling density): log(ms) interpolated linearly in dB between the two rows that bracket q.
        Returns (ms, True) when bracketed, (None, False) when q is outside the measured range."""
        pts = sorted((r["psnr_db"], r["ms"]) for r in rows if r["psnr_db"] is not None and math.isfinite(r["psnr_db"]))
        for (q0, t0), (q1, t1) in zip(pts, pts[1:]):
            if q0 <= q <= q1:
                w = 0.0 if q1 == q0 else (q - q0) / (q1 - q0)
                return math.exp((1 - w) * math.log(t0) + w * math.log(t1)), True
        return None, False

    def viewer(self):
        v, k = load(self.res, "viewer.json"), load(self.res, "viewer_vtk.json")
        self.w("## Viewer: frame time against PSNR\n")
        if not v:
            self.w("Not measured (viewer_bench not built or no GL).\n")
            return
        d = v["dims"]
        rounds = v.get("rounds", 1)
        self.w(f"Input: the packed phantom volume ({d[0]}×{d[1]}×{d[2]}, {v['levels']} levels), "
               f"{v['size']}×{v['size']} frame, azimuth 30°, elevation 20°, opacity {v['opacity']}; GL: "
               f"{v['gl']}. `scripts/bench/viewer_peers.py` runs vispack and the peer **interleaved**: "
               f"{rounds} rounds, each one `viewer_bench --file F --no-paged --reps {v.get('reps', 2)}` process "
               f"(the slice renderer, every density; median of {v.get('reps', 2)} frames after a warm-up, read-back "
               "included; the first round's process also runs the brick-paged measurements, before these) then one "
               "VTK process (every sample distance, the same number of frames); a row's frame time is the "
               "median over the rounds of the per-process medians.\n")
        self.w("**Quality is the foreground PSNR** of each renderer against its own finely sampled reference of "
               "the same transfer function: a pixel is foreground when its RGB differs from the black background "
               "in either image (no threshold), and PSNR = 10 log10(255² / MSE) with the MSE over the R, G, B of "
               "the foreground pixels only (`render::diff_foreground`; `psnr_foreground` in "
               "`scripts/bench/vtk_peer.py`). Over the whole frame the identical black background inflates the "
               "PSNR by 10 log10(frame / foreground) (whole-frame values kept in the last column). vispack's "
               "reference: its CPU reference ray caster at 8 steps per voxel, level 0 (a separate float "
               "implementation, so its PSNR includes the GL renderer's 8-bit blending, not only sampling). "
               "Levels of detail: the coarser levels' textures at 1 slice per voxel of that level, same "
               f"reference. First frame (open + coarsest level + frame, incl. context and shader compile): "
               f"{v['first_frame_s']:.2f} s; level-0 upload {v['upload_mb']:.1f} MB in {v['upload_s']:.2f} s.\n")
        rows = [[r["mode"], r["level"], fmt(r["slices_per_voxel"]), r["slices"], fmt(r["ms"]), fmt(r["psnr_db"]),
                 r.get("max_diff", "–"), fmt(r.get("psnr_whole_frame_db"))] for r in v["rows"]]
        self.w(table(["mode", "level", "slices / voxel", "slices", "frame ms", "foreground PSNR dB", "max diff",
                      "whole-frame PSNR dB"], rows))
        equal = None
        if k:
            self.w(f"Peer: VTK {self._vtk_version()} `vtkGPUVolumeRayCastMapper` offscreen on the same Mesa "
                   f"({k['renderer']}), the rgba channel from `vispack-extract` (level 0) as 4-component "
                   "RGBA, the same camera (eye, direction, up, field of view) and frame size, linear "
                   "interpolation, opacity from alpha scaled to the same opacity. Frame time includes "
                   "the read-back (`vtkWindowToImageFilter`). Foreground PSNR against VTK's own frame at a "
                   f"sample distance of {k['reference_sample_distance_voxels']} voxel: VTK's compositing and "
                   "transfer mapping differ from vispack's, so its PSNR against vispack's reference (last "
                   "column, foreground too) measures that difference, not sampling error. VTK first frame: "
                   f"{k['first_frame_s']:.2f} s.\n")
            rows = [[fmt(r["sample_distance_voxels"]), fmt(r["sample_distance_mm"], 2), fmt(r["ms"]), fmt(r["psnr_db"]),
                     r.get("max_diff", "–"), fmt(r.get("psnr_whole_frame_db")), fmt(r["psnr_vs_vispack_ref_db"])]
                    for r in k["rows"]]
            self.w(table(["sample distance (smallest voxel spacings)", "mm", "frame ms", "foreground PSNR dB (vs VTK fine)",
                          "max diff", "whole-frame PSNR dB", "foreground PSNR dB vs vispack reference"], rows))
            ours = [r for r in v["rows"] if r["mode"] == "colour" and r["level"] == 0]
            vtk1 = next((r for r in k["rows"] if r["sample_distance_voxels"] == 1.0), None)
            if ours and vtk1:
                q = vtk1["psnr_db"]
                ms, ok = self._ms_at_psnr(ours, q)
                if ok:
                    equal = (ms, q)
                    self.w(f"**At equal quality**: VTK at its default (1 sample per voxel) reaches {fmt(q)} dB "
                           f"foreground PSNR in {fmt(vtk1['ms'])} ms; along vispack's colour curve (level 0, "
                           "log time interpolated linearly in dB between the two densities that bracket it) "
                           f"the same {fmt(q)} dB takes {fmt(ms)} ms: **{ms / vtk1['ms']:.2f}×** VTK's time "
                           f"(vispack {'slower' if ms > vtk1['ms'] else 'faster'} than VTK at equal "
                           "foreground quality; both time one render and one read-back).\n")
                    self.summary.append([f"viewer frame at VTK's default quality ({fmt(q)} dB foreground PSNR)",
                                         f"{fmt(ms)} ms (interpolated)", f"VTK GPU ray caster, 1 sample/voxel: "
                                         f"{fmt(vtk1['ms'])} ms",
                                         f"{ms / vtk1['ms']:.2f}× VTK's time: vispack "
                                         f"{'slower' if ms > vtk1['ms'] else 'faster'}"])
                else:
                    lo = min(r["psnr_db"] for r in ours)
                    hi = max(r["psnr_db"] for r in ours)
                    self.w(f"**At equal quality**: VTK at its default (1 sample per voxel) reaches {fmt(q)} dB "
                           f"foreground PSNR in {fmt(vtk1['ms'])} ms, outside vispack's measured range "
                           f"({fmt(lo)}–{fmt(hi)} dB): no interpolated time (add densities to --spv).\n")
                    self.summary.append([f"viewer frame at VTK's default quality ({fmt(q)} dB)",
                                         f"not bracketed ({fmt(lo)}–{fmt(hi)} dB measured)",
                                         f"VTK GPU ray caster: {fmt(vtk1['ms'])} ms", "–"])
        fig, ax = plt.subplots(figsize=(7.5, 4.8))
        for mode in ("colour", "labels"):
            rs = [r for r in v["rows"] if r["mode"] == mode and r["level"] == 0]
            if rs:
                ax.plot([r["ms"] for r in rs], [r["psnr_db"] for r in rs], label=f"vispack {mode}, level 0 (slices/voxel)", **OURS)
                for r in rs:
                    ax.annotate(f"{r['slices_per_voxel']:g}", (r["ms"], r["psnr_db"]), textcoords="offset points", xytext=(4, 4), fontsize=8)
        lod = [r for r in v["rows"] if r["level"] > 0]
        if lod:
            ax.plot([r["ms"] for r in lod], [r["psnr_db"] for r in lod], "s", color="tab:green", markersize=8,
                    label="vispack colour, coarser levels (LOD)")
            for r in lod:
                ax.annotate(f"L{r['level']}", (r["ms"], r["psnr_db"]), textcoords="offset points", xytext=(4, -10), fontsize=8)
        if k:
            ax.plot([r["ms"] for r in k["rows"]], [r["psnr_db"] for r in k["rows"]],
                    label="VTK GPU ray caster (peer; foreground PSNR vs its own fine frame)", **PEER)
            for r in k["rows"]:
                ax.annotate(f"{r['sample_distance_voxels']:g} vx", (r["ms"], r["psnr_db"]), textcoords="offset points", xytext=(4, 4), fontsize=8, color="crimson")
        if equal:
            ax.plot([equal[0]], [equal[1]], "*", color="tab:blue", markersize=13, markeredgecolor="black",
                    label="vispack at VTK's 1-sample-per-voxel quality (interpolated)")
        ax.axhline(40, color="gray", linestyle=":", label="docs/GOALS.md goal: ≥ 40 dB at 2 slices / voxel")
        ax.set_xscale("log")
        plain_ticks(ax)
        ax.set_xlabel(f"frame time (ms, {v['size']}×{v['size']}, log scale)")
        ax.set_ylabel("foreground PSNR against the fine reference (dB)")
        ax.set_title("Viewer on llvmpipe: speed against error")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        self.save(fig, "viewer.png", "viewer frame time against PSNR")
        ref, vtkimg = os.path.join(self.res, "viewer_ref.png"), os.path.join(self.res, "viewer_vtk.png")
        if os.path.exists(ref) and os.path.exists(vtkimg):
            import matplotlib.image as mpimg
            fig, axs = plt.subplots(1, 2, figsize=(7, 3.6))
            for a, path, title in ((axs[0], ref, "vispack CPU reference"), (axs[1], vtkimg, "VTK GPU ray caster (peer)")):
                a.imshow(mpimg.imread(path))
                a.set_title(title, fontsize=9)
                a.axis("off")
            self.save(fig, "viewer_views.png", "the same view rendered by vispack and VTK")

    @staticmethod
    def _vtk_version():
        try:
            import vtk
            return vtk.vtkVersion.GetVTKVersion()
        except ImportError:
            return ""

    # ---- scaling ------------------------------------------------------------------------
    # ---- real size -----------------------------------------------------------

"""The stages one by one: time per slice, error against truth, and peak memory.
A section mixin of report.py's Report: self.w, self.save, self.res and the rest come from it."""

import numpy as np

from report_common import fmt, load, loglog_fit, plt, table  # noqa: E402


class StagesSection:
    def stages(self):
        st = load(self.res, "stages.json")
        self.w("## Each stage on one and two cores, with its error, against docs/GOALS.md §6\n")
        if not st:
            self.w("Not measured.\n")
            return
        n, w, h = st["slices"], st["width"], st["height"]
        ncmp = len(st["compared_slices"])
        left = n - ncmp
        self.w(f"Input: the `{st['phantom']}` phantom ({w}×{h}, {n} slices, `--preset {st['preset']}`"
               + (f", {left} of them black or duplicated" if left else "") + "). Each stage "
               "executable run alone, `vispack-STAGE --config C --force --quiet --threads T`, T = 1 then "
               "2, one run each, under `/usr/bin/time -v`. Wall: the stage's own time "
               "(`work/STAGE/report.json`: reading, work, writing) per slice. CPU: user + system time "
               "of the whole process (start-up included) per slice. On one thread the CPU time is what "
               "an idle core would take, while the wall time on this loaded machine waits for a core, "
               "so the one-core goals are judged on the 1-thread CPU time (both are shown). Errors "
               f"against the phantom's truth over the {ncmp} slices that can agree with it (black and "
               "duplicated slices left out): register, the RMS over the stack of each slice's "
               "cumulative transform error against `truth/transforms.json` (largest displacement of "
               "the four corners and the centre, the measure of `rigid_motion_px`; the error at the "
               "centre alone in brackets; reference slice left out); mask, IoU of "
               "`work/mask/mask_*.png` against `truth/mask.nrrd`; labels, % of body pixels equal to "
               "`truth/labels.nrrd` where the truth is uniform over 3×3 (away from edges); pack, "
               "level-0 raw bytes (as `vispack-extract` writes them) / file bytes (all levels), and its "
               "2-thread wall time against `zstd -3 -T2` of the same raw bytes"
               + (", the two interleaved (pack, zstd, pack, zstd, … three each; medians)"
                  if "pack_seconds" in st["zstd3_t2"] else " (median of 3, run after the stages, not interleaved)")
               + ".\n")
        by = {(r["stage"], r["threads"]): r for r in st["runs"]}
        z = st["zstd3_t2"]
        names = ("register", "mask", "labels", "pack", "vdb")

        def per(stage, t, key="stage_seconds"):
            r = by.get((stage, t))
            return r[key] / n if r else float("nan")

        def times(stage):
            return [fmt(per(stage, 1)), fmt(per(stage, 1, "cpu_seconds")), fmt(per(stage, 2)),
                    fmt(per(stage, 2, "cpu_seconds"))]

        def met(ok):
            return "**met**" if ok else "**not met**"

        e = by[("register", 1)]
        rows = []
        reg1 = per("register", 1, "cpu_seconds")
        rows.append(["register"] + times("register") +
                    [f"drift RMS {e['drift_rms_px']:.3f} px (centre {e.get('drift_centre_rms_px', float('nan')):.3f}), "
                     f"max {e['drift_max_px']:.3f}",
                     "≤ 0.25 s/slice on one core, ≤ 0.1 px RMS",
                     f"time {met(reg1 <= 0.25)}, error {met(e['drift_rms_px'] <= 0.1)}"])
        mask1 = per("mask", 1, "cpu_seconds")
        rows.append(["mask"] + times("mask") + [f"IoU {e['iou']:.4f}", "≤ 30 ms/slice, IoU ≥ 0.99",
                                                f"time {met(mask1 <= 0.030)}, IoU {met(e['iou'] >= 0.99)}"])
        rows.append(["labels"] + times("labels") + [f"{e['labels_equal_pct']:.3f} % equal away from edges",
                     "no time goal; exact with PNG segmentation",
                     met(e["labels_equal_pct"] >= 100.0) if e["labels_equal_pct"] >= 99.5 else "**not met**"])
        pk2 = by[("pack", 2)]
        raw = z["raw_bytes"]
        vs_zstd = z.get("pack_seconds", pk2["stage_seconds"]) / z["seconds"]
        rows.append(["pack"] + times("pack") +
                     [f"raw / file {raw / pk2['output_bytes']:.2f}× (`zstd -3`: {raw / z['bytes']:.2f}×); "
                      f"2-thread wall {vs_zstd:.2f}× `zstd -3 -T2` ({fmt(z['seconds'])} s)",
                      "within 1.25× of `zstd -3 -T2`", met(vs_zstd <= 1.25)])
        vd = by[("vdb", 2)]
        rows.append(["vdb"] + times("vdb") +
                     [f"not measured here (file {fmt(vd['output_bytes'] / 1e6)} MB, raw / file {raw / vd['output_bytes']:.2f}×)"
                      if vd.get("output_bytes") else "not measured here", "none in docs/GOALS.md §6", "–"])
        self.w(table(["stage", "wall s / slice, 1 thread", "CPU s / slice, 1 thread", "wall s / slice, 2 threads",
                      "CPU s / slice, 2 threads", "error against truth", "docs/GOALS.md §6 goal", "met?"], rows))
        sp = {s: per(s, 1) / per(s, 2) for s in names}
        self.w("Wall-time speed-up from the second thread: " + ", ".join(f"{s} {v:.2f}×" for s, v in sp.items())
               + " (the machine is shared: with the load average above, a second thread often finds no "
               f"free core). Whole stack, one thread: {fmt(sum(per(s, 1, 'cpu_seconds') for s in names))} CPU "
               f"s/slice ({fmt(sum(per(s, 1) for s in names))} wall); two threads: "
               f"{fmt(sum(per(s, 2) for s in names))} wall s/slice. Where each stage's time goes is in the "
               "profile section at the end.\n")
        # The stage executables also read and write PNG slices; the in-memory kernels are timed by
        # register_bench and mask_bench (sections below), which isolates the algorithm's share.
        reg, mk = load(self.res, "register.json"), load(self.res, "mask.json")
        notes = []
        if reg:
            d = next((r for r in reg["results"] if r.get("ecc_scale") == 0.5), None)
            if d:
                notes.append(f"registering one pair in memory (`register_bench`, phase + ECC at ecc_scale 0.5, "
                             f"{reg['width']}×{reg['height']}) takes {fmt(1e3 * d['cpu_seconds_per_pair'])} CPU ms "
                             f"against the stage's {fmt(1e3 * reg1)} CPU ms per slice, which also reads the colour "
                             "slices, aligns the CT and writes the registered slices")
        if mk:
            d = next((r for r in mk["rows"] if r["threads"] == 1 and "gel refinement" in r["method"]
                      and "no gel" not in r["method"]), None)
            if d:
                notes.append(f"the mask computation alone (`mask_bench`, one thread) takes "
                             f"{fmt(d['cpu_ms_per_slice'])} CPU ms per {mk['width']}×{mk['height']} slice "
                             f"({'within' if d['cpu_ms_per_slice'] <= 30 else 'over'} the 30 ms goal) against the "
                             f"stage's {fmt(1e3 * mask1)} ms, which also reads the registered colour and CT "
                             "slices and writes CT, mask and overlay PNGs")
        if notes:
            self.w("The anchors in docs/GOALS.md §6 time the computation alone (phase correlation 171 ms, Lab "
                   "threshold 40 ms); the stage times above are "
                   "end to end. For comparison, " + "; ".join(notes) + ".\n")
        self.summary.insert(0, ["stages vs docs/GOALS.md §6 (1 thread, per slice)",
                                f"register {fmt(reg1)} s, {e['drift_rms_px']:.3f} px; mask {fmt(1e3 * mask1)} ms, IoU {e['iou']:.4f}; "
                                f"pack {vs_zstd:.2f}× zstd's time",
                                "goals: 0.25 s, 0.1 px; 30 ms, 0.99; pack ≤ 1.25× zstd -3 -T2",
                                "see the table: met / not met per goal"])

    # ---- memory per stage ---------------------------------------------------------------

    def stage_memory(self):
        m = load(self.res, "stage_memory.json")
        self.w("## Memory as the work grows, per stage\n")
        if not m or not m["rows"]:
            self.w("Not measured.\n")
            return
        rows = m["rows"]
        counts = sorted({r["slices"] for r in rows})
        r0 = rows[0]
        self.w(f"Each stage executable run alone (`--threads 2`) under `/usr/bin/time -v` on "
               f"`{r0['phantom'].rsplit('-', 1)[0]}` phantoms of {r0['width']}×{r0['height']} with "
               f"{', '.join(map(str, counts))} slices; peak resident memory (\"Maximum resident set "
               "size\") in MiB. The pack writer holds one level-0 brick row (64 slices at the "
               "default brick edge; the coarser levels' partial slabs spill to a temporary file) by design, so the counts span several rows; a handful of vhp-size "
               "slices would all fall inside the first row and could not show flatness. Exponent: "
               "log-log least-squares slope of peak memory against the slice count (0 = flat, 1 = "
               "proportional to the volume).\n")
        # "run": the whole vispack-run in one process (stage_memory.py), the peak a user sees.
        stages = [s for s in ["register", "mask", "labels", "pack", "vdb", "run"] if any(r["stage"] == s for r in rows)]
        t, fits, growth, slope = [], {}, {}, {}
        for s in stages:
            rs = sorted((r for r in rows if r["stage"] == s), key=lambda r: r["slices"])
            a = loglog_fit([r["slices"] for r in rs], [r["peak_rss_mib"] for r in rs])[0] if len(rs) >= 2 else float("nan")
            fits[s] = 0.0 if abs(a) < 0.005 else a  # no "-0.00"
            growth[s] = rs[-1]["peak_rss_mib"] / rs[0]["peak_rss_mib"] - 1 if len(rs) >= 2 else 0.0
            slope[s] = (float(np.polyfit([r["slices"] for r in rs], [r["peak_rss_mib"] for r in rs], 1)[0])
                        if len(rs) >= 2 else 0.0)
            t.append([s] + [fmt(r["peak_rss_mib"]) for r in rs]
                     + [f"{100 * growth[s]:+.0f} %", fmt(100 * slope[s]), f"**{fits[s]:.2f}**"])
        self.w(table(["stage"] + [f"{c} slices, MiB" for c in counts]
                     + ["growth, first to last", "MiB per 100 slices (linear fit)", "exponent"], t))
        # The exponent of the whole RSS is diluted by the ~130 MiB every process maps (OpenCV,
        # OpenVDB, TBB): judge flatness by the growth itself.
        flat = [s for s in stages if growth[s] < 0.10]
        grow = [s for s in stages if growth[s] >= 0.10]
        base = min(r["peak_rss_mib"] for r in rows)
        text = (f"Even the lightest stage run peaks at {base:.0f} MiB (the process with its OpenCV, "
                "OpenVDB and TBB libraries), which dilutes the exponent of the whole resident size, so flatness is judged by the "
                f"growth itself (under 10 % from {counts[0]} to {counts[-1]} slices = flat). "
                f"Flat: {', '.join(f'{s} ({100 * growth[s]:+.0f} %)' for s in flat) or 'none'}. "
                f"**Not flat: {', '.join(f'{s} ({100 * growth[s]:+.0f} %, {fmt(100 * slope[s])} MiB per 100 slices)' for s in grow) or 'none'}.**")
        vdb_rows = [r for r in rows if r["stage"] == "vdb"]
        parts = [r for r in vdb_rows if r.get("vdb_layout") == "parts"]
        text += (" The OpenVDB export holds whole grids of what it writes (`openvdb::io::File::write` takes "
                 "in-memory grids), so at a fixed level one file's memory grows with the body's voxel count; "
                 "`vdb.layout` \"auto\" writes the level as z-slab parts, each within `vdb.max_memory_mb`, once "
                 "one file would exceed it (docs/ARCHITECTURE.md \"The OpenVDB export: one file or parts\"). "
                 + (f"Here {len(parts)} of {len(vdb_rows)} vdb runs wrote parts."
                    if parts else "These small stacks all fit one file at level 0, so vdb grows with them "
                    "up to the budget; the real-size section below shows the parts."))
        if "pack" in grow:
            text += (" pack grows too: beyond the brick row it holds, its peak includes the "
                     "pyramid's coarser levels; see the format details section.")
        elif "pack" in flat:
            text += (f" pack grows {100 * growth['pack']:.0f} % over {counts[-1] // counts[0]}× the slices: "
                     "close to flat, as the writer holds one brick row (the small remaining growth "
                     "is not analysed here).")
        self.w(text + "\n")
        self.summary.append(["peak memory per stage (small slices, " + "/".join(map(str, counts)) + ")",
                             ", ".join(f"{s} {100 * growth[s]:+.0f} %" for s in stages),
                             "flat = +0 %",
                             ("not flat: " + ", ".join(grow) + (" (whole OpenVDB grids in memory)" if "vdb" in grow else ""))
                             if grow else "all flat"])
        fig, ax = plt.subplots(figsize=(7.5, 4.8))
        for s, mk in zip(stages, "os^Dv*"):
            rs = sorted((r for r in rows if r["stage"] == s), key=lambda r: r["slices"])
            ax.plot([r["slices"] for r in rs], [r["peak_rss_mib"] for r in rs], marker=mk, linewidth=1.5,
                    label=f"{s} (∝ slices^{fits[s]:.2f})")
        ax.set_xscale("log", base=2)
        ax.set_xticks(counts)
        ax.set_xticklabels([str(c) for c in counts])
        ax.set_ylim(0, 1.2 * max(r["peak_rss_mib"] for r in rows))
        ax.set_xlabel(f"slices ({r0['width']}×{r0['height']} each, log scale)")
        ax.set_ylabel("peak resident memory (MiB)")
        ax.set_title("Peak memory of each stage run alone")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        self.save(fig, "stage_memory.png", "peak memory of each stage against the slice count")

    # ---- registration -------------------------------------------------------------------

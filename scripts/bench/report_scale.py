"""Cost as the work grows: the real slice size, the scaling with the stack, the profiles.
A section mixin of report.py's Report: self.w, self.save, self.res and the rest come from it."""
import json
import math
import os
import re

import numpy as np

from common import median  # noqa: E402
from report_common import OURS, fmt, load, loglog_fit, plt, table  # noqa: E402



def vdb_exported(report):
    """The OpenVDB export's level and layout from its stage report: "0", or "0 (3 parts)"."""
    level = report.get("chosen_level", report.get("level", "–"))
    return f"{level} ({report['parts']} parts)" if report.get("parts") else f"{level}"

class ScaleSection:
    def real_size(self):
        r = load(self.res, "real_size.json")
        self.w("## Whole pipeline at the real slice size\n")
        if not r or not r["runs"]:
            self.w("Not measured.\n")
            return
        n0 = r["counts"][0]
        first = [x for x in r["runs"] if x["slices"] == n0]
        one = [x for x in first if x["threads"] == 1]
        two = [x for x in first if x["threads"] == 2]
        mem = r["memory"]
        w, h = mem[0]["dims"][0], mem[0]["dims"][1]
        self.w(f"Input: stacks of {w}×{h} colour slices (planar `.raw`, as NLM ships them) with CT and "
               f"segmentation, {', '.join(map(str, r['counts']))} slices, linked in ping-pong order from the "
               f"`{r['base']}` phantom (`scripts/bench/real_size.py`: consecutive slices stay neighbours; the "
               "content repeats, so these runs measure cost and memory, not accuracy). "
               f"`vispack-run CONFIG --force --threads T` under `/usr/bin/time -v`; on {n0} slices T = 1 and 2 "
               f"interleaved, {r['reps']} rounds, medians. Load average at the start: "
               f"{', '.join(fmt(x) for x in r['load_at_start'])} (2 cores).\n")

        def med(rows, key):
            return median([x[key] for x in rows]) if rows else float("nan")

        stages = sorted({k for x in first for k in x["stages_s"]},
                        key=lambda k: ["register", "mask", "labels", "stream", "pack", "vdb"].index(k)
                        if k in ["register", "mask", "labels", "stream", "pack", "vdb"] else 99)
        rows = []
        for t, rs in ((1, one), (2, two)):
            if not rs:
                continue
            rows.append([t, fmt(med(rs, "wall_s") / n0), fmt(med(rs, "cpu_s") / n0), fmt(med(rs, "peak_rss_mib"))]
                        + [fmt(median([x["stages_s"].get(k, 0.0) for x in rs]) / n0) for k in stages])
        self.w(table(["threads", "wall s / slice", "CPU s / slice (whole process)", "peak RSS MiB"]
                     + [f"{k} wall s / slice" for k in stages], rows))
        cpu1 = med(one, "cpu_s") / n0 if one else float("nan")
        speedup = med(one, "wall_s") / med(two, "wall_s") if one and two else float("nan")
        male = 1871
        self.w(f"One thread: **{fmt(cpu1)} CPU s per slice** (goal ≤ 0.3: **{'met' if cpu1 <= 0.3 else 'not met'}**). "
               f"Two threads against one, wall time: **{speedup:.2f}×** (goal ≥ 1.7× on an idle machine: "
               f"**{'met' if speedup >= 1.7 else 'not met'}**"
               + ("; the machine was not idle, see the load above"
                  if r["load_at_start"][0] >= (os.cpu_count() or 2) - 0.5 else "") + "). "
               f"The NLM male (2048×1216×{male:,}), extrapolated linearly from these runs: "
               f"{fmt(cpu1 * male / 3600)} CPU hours on one thread, "
               f"{fmt(med(two, 'wall_s') / n0 * male / 3600)} h wall on two threads.\n")
        pz = r.get("pack_vs_zstd")
        if pz:
            ratio = pz["pack_wall_s"] / pz["zstd_wall_s"]
            self.w(f"Pack against `zstd -3 -T2` of the same level-0 raw bytes ({fmt(pz['raw_bytes'] / 2**20)} MiB, "
                   f"{pz['slices']} slices), interleaved, {r['reps']} rounds: `vispack-pack --force --threads 2` "
                   f"{fmt(pz['pack_wall_s'])} s (its own stage time {fmt(pz['pack_stage_s'])} s; it also rebuilds "
                   f"the registered colour and CT from the inputs and reads the masks and labels), zstd "
                   f"{fmt(pz['zstd_wall_s'])} s: **{ratio:.2f}×** (goal ≤ 1.25×: **{'met' if ratio <= 1.25 else 'not met'}**). "
                   + (f"The encoder alone on the same bytes (`format_writer_raw_bench`: a format Writer with the "
                      f"file's options fed the level-0 slices from memory, 2 threads, every level, statistics, "
                      f"checksums and the file, as the pack stage writes them; its reading of the bytes timed "
                      f"apart): {fmt(pz['writer_wall_s'])} s, {fmt(pz['writer_cpu_s'])} CPU s, against zstd's "
                      f"{fmt(pz['zstd_wall_s'])} s, {fmt(pz['zstd_cpu_s'])} CPU s: "
                      f"**{pz['writer_wall_s'] / pz['zstd_wall_s']:.2f}×** the wall time "
                      f"({pz['writer_cpu_s'] / pz['zstd_cpu_s']:.2f}× the CPU). " if "writer_wall_s" in pz else "")
                   + f"Stored: {fmt(pz['vpk_bytes'] / 2**20)} MiB with every level against zstd's "
                   f"{fmt(pz['zstd_bytes'] / 2**20)} MiB for level 0 alone "
                   f"({pz['vpk_bytes'] / pz['zstd_bytes']:.2f}×).\n")
            self.summary.append([f"pack vs zstd -3 -T2 ({w}×{h}, wall, interleaved)", f"{fmt(pz['pack_wall_s'])} s",
                                 f"{fmt(pz['zstd_wall_s'])} s", f"{ratio:.2f}× (goal ≤ 1.25×)"])
        depth = r.get("encoder_depth")
        if depth:
            drows = []
            for d in depth:
                ww = median([x["write_s"] for x in d["writer"]])
                zw = median([x["wall_s"] for x in d["zstd"]])
                drows.append([d["repeat"], n0 * d["repeat"], fmt(d["raw_bytes"] / 2**30),
                              fmt(ww), fmt(median([x["write_cpu_s"] for x in d["writer"]])),
                              fmt(zw), fmt(median([x["cpu_s"] for x in d["zstd"]])),
                              f"**{ww / zw:.2f}×**", f"{d['vpk_bytes'] / d['zstd_bytes']:.2f}×"])
            self.w(f"The encoder against `zstd -3 -T2` as the stack deepens (`format_writer_raw_bench --repeat R`: "
                   f"the {n0} slices' level-0 bytes fed R times over; zstd of the same bytes, each channel's R "
                   "copies one after the other, its input read into the page cache first; interleaved, "
                   f"{r['reps']} rounds, medians). The Writer's one-row slab is fresh memory on its first fill, "
                   "and fresh memory is dear on this VM (its free pages go back to the host, and a page "
                   "touched again faults twice): the deeper stacks show the encoder past that, as on a real "
                   "stack of hundreds of slices.\n")
            self.w(table(["R", "slices", "level-0 GiB", "encoder wall s", "encoder CPU s", "zstd wall s",
                          "zstd CPU s", "encoder / zstd (goal ≤ 1.25×)", "file / zstd size (all levels)"],
                         drows))
            last = depth[-1]
            ratio_deep = (median([x["write_s"] for x in last["writer"]])
                          / median([x["wall_s"] for x in last["zstd"]]))
            self.summary.append([f"pack encoder vs zstd -3 -T2, {n0 * last['repeat']} slices' worth",
                                 f"{fmt(median([x['write_s'] for x in last['writer']]))} s",
                                 f"{fmt(median([x['wall_s'] for x in last['zstd']]))} s",
                                 f"{ratio_deep:.2f}× (goal ≤ 1.25×)"])
        bound_mib = 300e6 / 2**20
        mrows = []
        for m in mem:
            limit = m["brick_row_mib"] + bound_mib
            mrows.append([m["slices"], fmt(m["run_peak_rss_mib"]), fmt(m.get("pack_peak_rss_mib")),
                          fmt(m.get("vdb_peak_rss_mib")), fmt(m["brick_row_mib"]), fmt(limit),
                          "**met**" if m.get("pack_peak_rss_mib", 1e18) <= limit else "**not met**",
                          vdb_exported(m.get("vdb_report", {}))])
        self.w("Peak resident memory (MiB) as the stack grows; the pack goal is one level-0 brick row of the "
               f"output (x × y × brick edge {mem[0]['brick_edge']} × {mem[0]['bytes_per_voxel']} bytes per voxel over "
               "the stored channels) + 300 MB, flat in the slice count:\n")
        self.w(table(["slices", "vispack-run (2 threads)", "vispack-pack", "vispack-vdb", "one brick row",
                      "pack goal: row + 300 MB", "pack within?", "vdb level exported (files)"], mrows))
        self.summary.append([f"whole pipeline, {w}×{h} (" + "/".join(map(str, r["counts"])) + " slices)",
                             f"{fmt(cpu1)} CPU s/slice on 1 thread; 2 threads {speedup:.2f}×",
                             "goals: ≤ 0.3 CPU s/slice; ≥ 1.7×",
                             "pack peak " + "/".join(fmt(m.get("pack_peak_rss_mib")) for m in mem) + " MiB"])
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        xs = [m["slices"] for m in mem]
        for key, label in (("run_peak_rss_mib", "vispack-run (whole pipeline, 2 threads)"),
                           ("pack_peak_rss_mib", "vispack-pack"), ("vdb_peak_rss_mib", "vispack-vdb")):
            if all(key in m for m in mem):
                ax.plot(xs, [m[key] for m in mem], label=label, **OURS)
        ax.plot(xs, [m["brick_row_mib"] + bound_mib for m in mem], color="gray", linestyle=":",
                label="pack goal: one brick row + 300 MB")
        ax.set_xlabel(f"slices ({w}×{h} each)")
        ax.set_ylabel("peak resident memory (MiB)")
        ax.set_ylim(bottom=0)
        ax.set_title("Peak memory at the real slice size")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        self.save(fig, "real_size_memory.png", "peak memory against the slice count at 2048x1216")

    def startup(self):
        """Every executable's start-up (scripts/bench/startup.py --per-exe, run by scripts/bench.sh)."""
        s = self.section("Process start-up per executable", "startup_per_exe.json",
                         "Not measured (a `--quick` run skips it).")
        if not s:
            return
        rows = [(r["exe"], r["versions"][0]) for r in s["rows"]]
        self.w(f"`scripts/bench/startup.py --per-exe OUT {s['reps']} BIN` (run by `scripts/bench.sh`): "
               f"every `vispack-*` executable run as `EXE --help` (loads its libraries, does no work), "
               f"median of {s['reps']}; CPU = user + system of the child (the load-independent measure; "
               "the wall time mostly waits for a core on a loaded machine); libraries = `ldd`'s lines; "
               "relocations = symbol + relative relocations from `LD_DEBUG=statistics`. Load average "
               f"when it started: {', '.join(fmt(x) for x in s['load_average'])} (1, 5, 15 min).\n")
        self.w(table(["executable", "links OpenImageIO", "libraries", "relocations", "CPU ms", "wall ms"],
                     [[name, "yes" if v["openimageio"] else "no", v["libraries"], f"{v['relocations']:,}",
                       fmt(v["cpu_ms"]), fmt(v["wall_ms"])] for name, v in rows]))
        oiio = [v for _, v in rows if v["openimageio"]]
        other = [(n, v) for n, v in rows if not v["openimageio"]]
        if oiio and other:
            self.w(f"The {len(oiio)} executables that link OpenImageIO (every one that reads or writes "
                   "an image, through `vispack_image_io` / `slice_io`) load "
                   f"{min(v['libraries'] for v in oiio)}–{max(v['libraries'] for v in oiio)} libraries and "
                   f"spend a median {fmt(median([v['cpu_ms'] for v in oiio]))} CPU ms starting; "
                   + "; ".join(f"{n} (no OpenImageIO) {v['libraries']} libraries, {fmt(v['cpu_ms'])} ms"
                               for n, v in other) + ".\n")

    def scaling(self):
        path = os.path.join(self.res, "scaling.tsv")
        self.w("## Cost as the work grows: whole pipeline\n")
        if not os.path.exists(path):
            self.w("Not measured.\n")
            return
        rows = [json.loads(l) for l in open(path) if l.strip()]
        stage_names = ["register", "mask", "labels", "pack", "vdb"]
        su = load(self.res, "startup.json")
        su_cpu = su["cpu_seconds"] if su else 0.0
        self.w("`/usr/bin/time -v vispack-run CONFIG --force` (register → mask → labels → pack → vdb, all "
               "cores, in one process) on phantoms of growing size, one run each: wall time, CPU time "
               "(user + system) and peak resident memory (\"Maximum resident set size\"). Stage work: "
               "the sum of the per-stage times `vispack-run` reports, which leaves out the process "
               "start-up (loading OpenCV, OpenVDB, TBB; reading the config)."
               + (f" Start-up measured apart as `{su['command']}` (loads every library, does no work), "
                  f"median of {su['reps']}: {fmt(su['seconds'])} s wall, {fmt(su_cpu)} s CPU; the column "
                  "CPU − start-up subtracts it." if su else " Start-up was not measured in this run.") + "\n")

        def work(r):
            return sum(r["stages"].get(s, 0.0) for s in stage_names)

        t = []
        for r in rows:
            t.append([r["name"], f"{r['width']}×{r['height']}×{r['slices']}", fmt(r["voxels"] / 1e6), fmt(r["seconds"]),
                      fmt(r["cpu_seconds"]), fmt(r["cpu_seconds"] - su_cpu) if su else "–", fmt(work(r)),
                      fmt(1e9 * r["cpu_seconds"] / r["voxels"]), fmt(r["peak_rss_mib"])]
                     + [fmt(r["stages"].get(s)) for s in stage_names])
        self.w(table(["phantom", "size", "Mvoxels", "wall s", "CPU s", "CPU − start-up s", "stage work s (wall)",
                      "CPU ns / voxel", "peak RSS MiB"] + [f"{s} s" for s in stage_names], t))
        if len(rows) >= 2:
            vox = [r["voxels"] for r in rows]
            a_wall, _ = loglog_fit(vox, [r["seconds"] for r in rows])
            a_cpu, b_cpu = loglog_fit(vox, [r["cpu_seconds"] for r in rows])
            a_work, _ = loglog_fit(vox, [max(work(r), 1e-6) for r in rows])
            net = [r["cpu_seconds"] - su_cpu for r in rows]
            a_net = loglog_fit(vox, net)[0] if su and min(net) > 0 else float("nan")
            self.w(f"Fitted exponents (log-log least squares, all rows; 1.00 = linear). Work without the "
                   f"process start-up: stage work (wall) ∝ voxels^**{a_work:.2f}**"
                   + (f", CPU − start-up ∝ voxels^**{a_net:.2f}**" if math.isfinite(a_net) else "")
                   + f". Whole process, start-up included: wall ∝ voxels^{a_wall:.2f}, CPU ∝ voxels^{a_cpu:.2f}; "
                   "the fixed start-up is a large share of the small runs, so these whole-process "
                   "exponents understate how the work grows and are not a measure of scaling. The stage "
                   "times still hold each stage's own fixed costs (opening files, thread pools), so even "
                   "the work exponent is a lower bound on the per-slice growth at small sizes.")
            vhp = [r for r in rows if r["preset"] == "vhp"]
            if len(vhp) >= 2:
                a_mem, _ = loglog_fit([r["slices"] for r in vhp], [r["peak_rss_mib"] for r in vhp])
                a_vt, _ = loglog_fit([r["slices"] for r in vhp], [r["cpu_seconds"] for r in vhp])
                self.w(f" At the vhp slice size ({vhp[0]['width']}×{vhp[0]['height']}), over "
                       f"{', '.join(str(r['slices']) for r in vhp)} slices: CPU time ∝ slices^**{a_vt:.2f}**, "
                       f"peak memory ∝ slices^**{a_mem:.2f}** (0 = flat in the slice count). These few "
                       "vhp-size slices all sit inside the pack writer's first brick row (64 slices), which "
                       "it holds by design, so memory rises with them here; whether memory stays flat "
                       "over several brick rows is measured per stage in the memory section below.")
                self.summary.append(["pipeline scaling", f"stage work ∝ voxels^{a_work:.2f} (start-up excluded; "
                                     f"whole process incl. start-up: CPU ∝ voxels^{a_cpu:.2f})", "linear = 1.00",
                                     f"memory ∝ slices^{a_mem:.2f} at vhp size, {vhp[0]['slices']}–{vhp[-1]['slices']} slices (inside one brick row)"])
            self.w("\n")
            fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
            a1.loglog(vox, [r["seconds"] for r in rows], "o", label="vispack-run wall time")
            a1.loglog(vox, [r["cpu_seconds"] for r in rows], "s", label="vispack-run CPU time (start-up included)")
            a1.loglog(vox, [max(work(r), 1e-6) for r in rows], "^", label=f"stage work, wall (∝ voxels^{a_work:.2f})")
            if su:
                a1.axhline(su_cpu, color="gray", linestyle=":", label="process start-up, CPU (vispack-run --help)")
            xs = np.geomspace(min(vox), max(vox), 50)
            a1.loglog(xs, np.exp(b_cpu) * xs ** a_cpu, "-", color="gray", label=f"fit: CPU incl. start-up ∝ voxels^{a_cpu:.2f}")
            for r in rows:
                a1.annotate(r["name"], (r["voxels"], r["seconds"]), textcoords="offset points", xytext=(4, 4), fontsize=8)
            a1.set_xlabel("voxels (log scale)")
            a1.set_ylabel("time (s, log scale)")
            a1.set_title("Whole-pipeline time")
            series = [("phantom presets (slice size and count grow)", [r for r in rows if r["preset"] != "vhp"], "o-"),
                      (f"vhp slice size, {', '.join(str(r['slices']) for r in rows if r['preset'] == 'vhp')} slices",
                       [r for r in rows if r["preset"] == "vhp"], "s-")]
            for label, rs, style in series:
                rs = sorted(rs, key=lambda r: r["voxels"])
                if rs:
                    a2.semilogx([r["voxels"] for r in rs], [r["peak_rss_mib"] for r in rs], style, label=f"peak RSS: {label}")
            for r in rows:
                a2.annotate(r["name"], (r["voxels"], r["peak_rss_mib"]), textcoords="offset points", xytext=(4, 4), fontsize=8)
            a2.set_xlabel("voxels (log scale)")
            a2.set_ylabel("peak resident memory (MiB)")
            a2.set_ylim(bottom=0)
            a2.set_title("Peak memory")
            for a in (a1, a2):
                a.grid(True, which="both", alpha=0.3)
                a.legend(fontsize=8)
            self.save(fig, "scaling.png", "pipeline time and memory against volume size")

    # ---- profiles -----------------------------------------------------------------------
    # What a library's share of the samples says, and what would make that part faster.
    LIB_ADVICE = [
        ("ld-linux", "process start-up (dynamic symbol lookup: ~260 shared libraries, nearly all "
         "pulled in by OpenImageIO; section \"Process start-up per executable\")",
         "it is paid once per process, so run the stages in one process (`vispack-run`) or read "
         "and write PNG/TIFF without OpenImageIO; it matters only for small inputs"),
        ("libpng", "PNG decoding/encoding of slices and intermediates",
         "raw or zstd-1 intermediates instead of PNG between stages"),
        ("libz", "zlib (PNG and gzip) compression",
         "raw or zstd intermediates instead of PNG (zlib is the slowest codec in the chain)"),
        ("libzstd", "zstd compression", "a lower zstd level or more compression threads (see the pack sweep)"),
        ("libopencv", "OpenCV image processing (warps, filters, morphology, ECC)",
         "fewer full-resolution passes: work at a reduced scale where the error plots allow it, and "
         "restrict edge refinement to a band around the outline"),
        ("libopenvdb", "OpenVDB tree building and writing",
         "building leaf nodes from dense bricks (`openvdb::tools::copyFromDense`) instead of per-voxel access"),
        ("libtbb", "TBB scheduling (OpenVDB's and OpenCV's thread pools)", "larger work items per task"),
        ("kernel", "the kernel (file I/O, page faults, memory mapping)", "fewer, larger reads and writes"),
        ("libc", "libc (memcpy/memset, allocation)", "fewer copies of whole slices between steps"),
        ("libm", "libm (transcendental functions)", "tables or cheaper approximations in inner loops"),
    ]

    def _parse_profile(self, path):
        rows = []
        for line in open(path):
            m = re.match(r"\s*([\d.]+)%\s+(\S+)\s+\[(.)\]\s+(.*?)\s{2,}", line + "  ")
            if m:
                rows.append((float(m.group(1)), m.group(2), m.group(4).strip(), m.group(3) == "k"))
            else:
                m = re.match(r"\s*([\d,]+)\s+\(\s*([\d.]+)%\)\s+(.*)", line)
                if m:
                    sym = m.group(3).strip()
                    lib = sym.split(":")[0].split("/")[-1] if ":" in sym else ""
                    rows.append((float(m.group(2)), lib, sym.split(":", 1)[-1], False))
        return rows

    def _lib_group(self, lib, kernel):
        if kernel or lib.startswith("[kernel"):
            return "kernel"
        for key, _, _ in self.LIB_ADVICE:
            if key != "kernel" and lib.startswith(key):
                return key
        return lib

    def profiles(self):
        d = os.path.join(self.res, "profile")
        self.w("## Where the time goes, per stage\n")
        if not os.path.isdir(d):
            self.w("Not profiled in this run (`--quick` skips profiles).\n")
            return
        tool = open(os.path.join(d, "tool.txt")).read().strip()
        self.w(f"Profiler: {tool}, each stage run alone (`vispack-STAGE --config C --force`) on the "
               "volume phantom of the pack section. Top functions by self time (share of the stage's "
               "samples, entries under 1.5 % left out; `perf stat -e instructions` is not supported in "
               "this container, so sampling uses the cpu-clock software event). The reading under each "
               "table is derived from the libraries' shares; the remedies named are suggestions, not "
               "measurements.\n")
        advice = {k: (what, fix) for k, what, fix in self.LIB_ADVICE}
        for stage in ["register", "mask", "labels", "pack", "vdb"]:
            f = os.path.join(d, stage + ".txt")
            if not os.path.exists(f):
                continue
            rows = self._parse_profile(f)
            self.w(f"### {stage}\n")
            if not rows:
                self.w("(no samples above the threshold)\n")
                continue
            shown = []
            for pct, lib, sym, _ in rows[:8]:
                if len(sym) > 90:
                    sym = sym[:87] + "..."
                shown.append([f"{pct:.1f} %", f"`{lib}`", f"`{sym}`"])
            self.w(table(["self time", "library", "function"], shown))
            groups = {}
            for pct, lib, _, kernel in rows:
                g = self._lib_group(lib, kernel)
                groups[g] = groups.get(g, 0.0) + pct
            top = sorted(groups.items(), key=lambda kv: -kv[1])[:2]
            lines = []
            for g, pct in top:
                if g in advice:
                    what, fix = advice[g]
                    lines.append(f"{pct:.0f} % of the stage's samples are in {what}; faster: {fix}.")
                else:
                    names = [sym for _, lib, sym, _ in rows if self._lib_group(lib, False) == g][:2]
                    lines.append(f"{pct:.0f} % are in the program's own code (`{g}`: "
                                 + ", ".join(f"`{n[:60]}`" for n in names)
                                 + "); faster: optimise or parallelise these loops first.")
            self.w(" ".join(lines) + "\n")

"""The pack sweep and its peers, and the format's details.
A section mixin of report.py's Report: self.w, self.save, self.res and the rest come from it."""
import os


from report_common import OURS, PEER, fmt, load, plt, table  # noqa: E402


class PackSection:
    def pack(self):
        p = load(self.res, "pack.json")
        self.w("## Pack: stored size and throughput against zstd level and brick edge\n")
        if not p:
            self.w("Not measured.\n")
            return
        raw = p["raw_bytes"]
        self.w(f"Input: the `{p['preset']}` phantom after the pipeline ran; level-0 raw voxels "
               f"{raw / 1e6:.1f} MB (rgba8 {p['channels']['rgba'] / 1e6:.1f} MB, ct int16 "
               f"{p['channels']['ct'] / 1e6:.1f} MB, labels {p['channels']['labels'] / 1e6:.1f} MB, as "
               "`vispack-extract` writes them). `vispack-pack --config C --force --threads 2` per "
               f"setting, median of {p['reps']} runs; its time covers reading the mask/label "
               "intermediates (PNG), rebuilding the registered colour and the CT on the output grid "
               "from the input slices, building every pyramid level, statistics, checksums and "
               "compression, so it does more than the peers, which only compress bytes already in "
               "memory/page cache. Throughput = level-0 raw MB / wall time. Every setting and every "
               f"peer below runs once per repetition, round-robin (interleaved), median of {p['reps']}"
               + ("" if p.get("interleaved") else " (**this result file predates interleaving: the "
                  "settings and peers ran in separate blocks**)") + ".\n")
        rows = []
        for r in p["rows"]:
            rows.append([r["brick_edge"], r["zstd_level"], fmt(r["seconds"]), fmt(r["cpu_seconds"]),
                         fmt(raw / 1e6 / r["seconds"]), fmt(r["bytes"] / 1e6), fmt(raw / r["bytes"])])
        self.w(table(["brick edge", "zstd level", "wall s", "CPU s", "MB/s (raw / wall)", "file MB (all levels)",
                      "level-0 raw / file"], rows))
        peers = []
        for z in p["zstd"]:
            peers.append([f"`zstd -{z['zstd_level']} -T2` of the raw level-0 bytes", fmt(z["seconds"]), fmt(z["cpu_seconds"]),
                          fmt(raw / 1e6 / z["seconds"]), fmt(z["bytes"] / 1e6), fmt(raw / z["bytes"])])
        g = p["gzip_nrrd"]
        peers.append(["gzip-compressed NRRD (`gzip -6` payload, one per channel)", fmt(g["seconds"]), fmt(g["cpu_seconds"]),
                      fmt(raw / 1e6 / g["seconds"]), fmt(g["bytes"] / 1e6), fmt(raw / g["bytes"])])
        v = p["vdb"]
        peers.append(["vispack's own OpenVDB export, **not an independent peer** (`vispack-vdb`: different "
                      "content: ct float, labels int32, rgb vec3s, level 0 only, active voxels in the body only)",
                      fmt(v["seconds"]), fmt(v["cpu_seconds"]), fmt(raw / 1e6 / v["seconds"]), fmt(v["bytes"] / 1e6),
                      fmt(raw / v["bytes"])])
        default = next((r for r in p["rows"] if r["brick_edge"] == 64 and r["zstd_level"] == 3), p["rows"][0])
        peers.append([f"vispack .vpk default (edge {default['brick_edge']}, zstd {default['zstd_level']}, all levels)",
                      fmt(default["seconds"]), fmt(default["cpu_seconds"]), fmt(raw / 1e6 / default["seconds"]),
                      fmt(default["bytes"] / 1e6), fmt(raw / default["bytes"])])
        self.w("Peers on the same volume, same run, interleaved with the settings above. The OpenVDB row "
               "is vispack's own `vispack-vdb` export, not a third-party writer of the same data: it "
               "stores other content (float CT, int32 labels, float RGB without alpha, level 0 only, "
               "only the voxels inside the body), so its size and time are context, not a like-for-like "
               "comparison.\n")
        self.w(table(["file", "wall s", "CPU s", "MB/s", "MB", "raw / file"], peers))
        z3 = next((z for z in p["zstd"] if z["zstd_level"] == 3), p["zstd"][0])
        self.w(f"The default .vpk (every level) is {default['bytes'] / z3['bytes']:.2f}× the size of "
               f"`zstd -{z3['zstd_level']} -T2` of level 0 alone, {default['bytes'] / v['bytes']:.2f}× the size of "
               f"vispack's own OpenVDB export (other content: level 0 only, body voxels only) and {default['bytes'] / g['bytes']:.2f}× the size of the gzip NRRDs "
               "(level 0 only); packing (with its "
               f"intermediates, pyramid and checksums) takes {default['seconds'] / z3['seconds']:.1f}× the wall "
               f"time of `zstd -{z3['zstd_level']} -T2`.\n")
        self.summary.append(["pack (default .vpk, all levels)", f"{fmt(default['bytes'] / 1e6)} MB, {fmt(default['seconds'])} s",
                             f"zstd -{z3['zstd_level']} -T2: {fmt(z3['bytes'] / 1e6)} MB, {fmt(z3['seconds'])} s; "
                             f"gzip NRRD {fmt(g['bytes'] / 1e6)} MB (vispack's own OpenVDB export, other "
                             f"content: {fmt(v['bytes'] / 1e6)} MB)",
                             f"{default['bytes'] / z3['bytes']:.2f}× zstd's size, {default['seconds'] / z3['seconds']:.1f}× its time"])
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
        for edge in sorted({r["brick_edge"] for r in p["rows"]}):
            rs = [r for r in p["rows"] if r["brick_edge"] == edge]
            a1.plot([r["zstd_level"] for r in rs], [r["bytes"] / 1e6 for r in rs], label=f"vispack, brick edge {edge}", **OURS)
            a2.plot([r["zstd_level"] for r in rs], [raw / 1e6 / r["seconds"] for r in rs], label=f"vispack, brick edge {edge}", **OURS)
        zs = p["zstd"]
        a1.plot([z["zstd_level"] for z in zs], [z["bytes"] / 1e6 for z in zs], label="zstd -T2 (peer, level 0 only)", **PEER)
        a2.plot([z["zstd_level"] for z in zs], [raw / 1e6 / z["seconds"] for z in zs], label="zstd -T2 (peer)", **PEER)
        a1.axhline(v["bytes"] / 1e6, color="purple", linestyle=":", label="vispack's own OpenVDB export (other content, not a peer)")
        a1.axhline(g["bytes"] / 1e6, color="saddlebrown", linestyle="-.", label="gzip NRRD (peer)")
        a2.axhline(raw / 1e6 / g["seconds"], color="saddlebrown", linestyle="-.", label="gzip -6 NRRD (peer)")
        a2.axhline(raw / 1e6 / v["seconds"], color="purple", linestyle=":", label="vispack's own OpenVDB export (not a peer)")
        for a in (a1, a2):
            a.set_xticks(sorted({r["zstd_level"] for r in p["rows"]}))
        a1.set_xlabel("zstd level")
        a1.set_ylabel("stored size (MB)")
        a1.set_title("Stored size")
        a2.set_xlabel("zstd level")
        a2.set_ylabel("throughput (raw level-0 MB per wall second, log)")
        a2.set_yscale("log")
        a2.set_title("Throughput")
        for a in (a1, a2):
            a.grid(True, alpha=0.3)
            a.legend(fontsize=7)
        self.save(fig, "pack.png", "pack size and throughput against zstd level and brick edge")

    # ---- viewer -------------------------------------------------------------------------

    def format_details(self):
        f = os.path.join(self.res, "format_bench.md")
        if os.path.exists(f):
            self.w("## Format details (`format_bench`)\n")
            self.w(open(f).read().strip() + "\n")

    def store_size(self):
        """Stored size against the OpenVDB export and zstd -3 of the same content, and the work
        folder against the input (scripts/bench/store_size.sh, run by scripts/bench.sh)."""
        r = self.section("Stored size and intermediates", "store_size.json",
                         "Not measured (a `--quick` run skips it).")
        if not r:
            return
        self.w(f"Command: `scripts/bench/store_size.sh BIN WORK {r['slices']}` (run by "
               "`scripts/bench.sh`). Input: the `vhp` phantom (`vispack-phantom --preset vhp --slices "
               f"{r['slices']} --rgb-raw --seed 1`: 2048×1216 colour as planar `.raw` as NLM ships it, "
               "512² CT, segmentation), run by `vispack-run` with the defaults, then repacked by "
               "`vispack-pack --force` with `pack.keep_outside_body: \"all\"` (the gel kept) and with "
               "`pack.crop_margin_px: 16`. The zstd peer compresses **the same file's own content**: "
               "every channel of that file at level 0 as `vispack-extract` writes it (NRRD, raw), "
               "concatenated, `zstd -3 -T1`. The OpenVDB export (`vispack-vdb`: float CT, int32 labels, "
               "three floats of colour, body voxels only, level 0 only) stores 20 bytes a voxel against "
               f"the packed file's {r['vpk_bytes_per_voxel']:.1f} (rgba8, int16 CT, uint8 or uint16 "
               "labels), so most of the ratio against it is type width: it is also given at equal "
               "widths (OpenVDB's standard grids have no 8- or 16-bit types to export to). The packed "
               "file holds every level of the pyramid and its brick index; the zstd peer level 0 "
               "only, as one stream.\n")
        text = open(os.path.join(self.res, "store_size.md")).read() if os.path.exists(
            os.path.join(self.res, "store_size.md")) else ""
        self.w(text.rstrip() + "\n")
        met = lambda ok: "**met**" if ok else "**not met**"
        self.w(f"Goals (docs/GOALS.md §6): stored size ≤ 0.5× the OpenVDB export: "
               f"{met(r['vpk_over_vdb'] <= 0.5)} as stored ({r['vpk_over_vdb']:.2f}×), "
               f"{met(r['vpk_over_vdb_equal_width'] <= 0.5)} at equal type widths "
               f"({r['vpk_over_vdb_equal_width']:.2f}×); < `zstd -3` of the raw bytes of the same "
               f"content: {met(r['vpk_over_zstd'] < 1)} ({r['vpk_over_zstd']:.2f}×; with the gel kept "
               f"{r['vpk_keep_over_zstd']:.2f}×); intermediates ≤ 15 % of the input: "
               f"{met(r['work_over_input'] <= 0.15)} ({100 * r['work_over_input']:.1f} %). The packed "
               f"file is {100 * r['vpk_over_input']:.1f} % of the input slices' bytes.\n")
        self.summary.append(["stored size, same content (vhp phantom, 2048×1216)",
                             f"{r['vpk_default'] / 1e6:.1f} MB (every level)",
                             f"`zstd -3` of level 0: {r['zstd3_raw_level0'] / 1e6:.1f} MB",
                             f"{r['vpk_over_zstd']:.2f}×"])

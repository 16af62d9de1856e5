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

    def ome_zarr(self):
        """The OME-Zarr export against vispack-extract writing NRRD, at the real slice size
        (scripts/bench/ome_zarr_export.sh, run by scripts/bench.sh)."""
        r = self.section("OME-Zarr export against NRRD extraction", "ome_zarr_export.json",
                         "Not measured (a `--quick` run skips it).")
        if not r:
            return
        ex, v4, nc, v5 = r["extract"], r["v04"], r["v04_nocopy"], r["v05"]
        vpk = r["vpk_bytes"]
        n_ch = len(r["channels"])
        self.w(f"Command: `scripts/bench/ome_zarr_export.sh BIN WORK {r['slices']} {r['threads']} OUT.json "
               f"{r['rounds']}` (run by `scripts/bench.sh`). Input: the `vhp` phantom at the real size, "
               f"`vispack-phantom --preset vhp --slices {r['slices']} --rgb-raw --seed 1` packed by "
               f"`vispack-run` (OpenVDB export off): 2048×1216×{r['slices']}, channels "
               f"{', '.join(r['channels'])}, {r['levels']} levels, {vpk:,} bytes. Each row is one process "
               f"(extract: one per channel and level, {n_ch * r['levels']}, summed; peak = the largest) "
               "under `/usr/bin/time -v`, the .vpk in the page cache; export with "
               f"`--threads {r['threads']}`, every channel and level; sizes are the bytes of every file "
               f"written. {r['rounds']} rounds, each running every row once in the order of the table "
               "(interleaved); times and peaks are the medians over the rounds. Load average "
               f"{', '.join(f'{x:.1f}' for x in r['load_average_start'])} (1, 5, 15 min) when the rows "
               f"started, {', '.join(f'{x:.1f}' for x in r['load_average_end'])} when they ended: on "
               "the shared machine CPU time (user + system) is the measure to compare, wall time is "
               "inflated by the load.\n")
        rows = []
        for label, x in (("`vispack-extract`, every channel and level as NRRD", ex),
                         ("`vispack-export --ngff 0.4`", v4),
                         ("`vispack-export --ngff 0.4 --no-copy`", nc),
                         ("`vispack-export --ngff 0.5` (default shards)", v5)):
            cpu = x["cpu_s_rounds"]
            rows.append([label, f"{x['wall_s']:.2f}", f"{x['cpu_s']:.2f} ({min(cpu):.2f}–{max(cpu):.2f})",
                         f"{x['peak_mib']:.1f}", f"{x['bytes']:,}", f"{x['bytes'] / vpk:.2f}", x["files"]])
        self.w(table(["run", "wall s", "CPU s (range)", "peak MiB", "output bytes", "× .vpk", "files"], rows))
        met = lambda ok: "**met**" if ok else "**not met**"
        peak = max(v4["peak_mib"], nc["peak_mib"], v5["peak_mib"])
        per_shard = v5["chunk_files"] / max(v5["shards"], 1)
        size = max(v4["bytes"], v5["bytes"]) / vpk
        self.w(f"- Against the export's targets: output ≤ 1.1× the `.vpk`: {met(size <= 1.1)} "
               f"({v4['bytes'] / vpk:.2f}× for 0.4, {v5['bytes'] / vpk:.2f}× for 0.5); peak memory "
               f"≤ 300 MB: {met(peak * 1.048576 <= 300)} ({peak:.0f} MiB); NGFF 0.5 one file per shard: "
               f"{met(per_shard == 1)} ({v5['chunk_files']} chunk files for {v5['shards']} shards, "
               f"{v5['files']} files in all with the metadata, where 0.4 writes one file per chunk, "
               f"{v4['files']} in all). The export takes {v4['cpu_s'] / ex['cpu_s']:.2f}× (0.4) and "
               f"{v5['cpu_s'] / ex['cpu_s']:.2f}× (0.5) the CPU of `vispack-extract` writing the same "
               f"channels and levels as NRRD ({v4['wall_s'] / ex['wall_s']:.2f}× and "
               f"{v5['wall_s'] / ex['wall_s']:.2f}× the wall time).")
        self.w(f"- Chunks (counted over the images: the rgba channel gives two, colour and alpha): "
               f"{v4['chunks_copied']:,} copied (CT and label bricks whose stored zstd frame is the "
               f"chunk), {v4['chunks_encoded']:,} encoded (colour and alpha, which must be transposed out "
               "of the interleaved rgba, and constant bricks not equal to the fill value), "
               f"{v4['chunks_fill']:,} not written (equal to the fill value: air, gel, unlabelled).")
        saved = nc["cpu_s"] - v4["cpu_s"]
        self.w(f"- The copy of stored bricks saves {saved:.2f} s of {nc['cpu_s']:.2f} s CPU "
               f"({100 * saved / nc['cpu_s']:.0f} %; {nc['wall_s'] - v4['wall_s']:.1f} s of "
               f"{nc['wall_s']:.1f} s wall) at this size (0.4 against 0.4 `--no-copy`): what remains "
               "is mostly the colour, decoded and re-encoded.")
        self.w("- Peak memory: the export releases each brick's mapped pages once written "
               "(`Reader::release_payload_pages`), so the pages of the memory-mapped `.vpk` do not "
               "count in the resident set; the peak is the bricks in flight (a batch per thread) and "
               "does not grow with the file.")
        self.w(f"- Sizes: 0.5 is {100 * (v5['bytes'] / v4['bytes'] - 1):.1f} % larger than 0.4 (each "
               "shard's index: 16 bytes per inner chunk slot + a crc32c); "
               + ("both are smaller than the `.vpk`" if size < 1 else "against the `.vpk`")
               + ", which stores every brick including the uniform ones' index entries and the label sets, "
               "pads payloads to 4 KiB, and keeps alpha interleaved.\n")

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

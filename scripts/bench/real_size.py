#!/usr/bin/python3
"""The numbers at the real slice size: the whole pipeline (`vispack-run`) on stacks of
2048x1216 colour slices growing past several brick rows, its CPU time per slice on one and two
threads, the pack stage against `zstd -3 -T2` of the same level-0 bytes, and the peak memory of
the whole run, of the pack stage and of the OpenVDB export as the stack grows.

Usage: real_size.py BASE_PHANTOM OUT_JSON SLICES... (e.g. 128 256 512)
BASE_PHANTOM: a `vispack-phantom --preset vhp --rgb-raw` folder (planar .raw colour as NLM ships
it). A stack of N slices is built from its slices by symbolic links, in ping-pong order (0, 1, ...,
last, last, ..., 1, 0, 0, 1, ...): consecutive slices stay neighbours, so registration sees the
phantom's drift (reversed every period) and nothing else; the turning points are duplicated
slices, which the pipeline flags as it flags any duplicate. The content repeats, so these stacks
measure cost and memory, not accuracy (accuracy is measured on the phantoms with their truth).

For the smallest N: `vispack-run --force --threads T` for T = 1 and 2, interleaved (1, 2, 1, 2,
REPS rounds; medians), then `vispack-pack --force --threads 2`, the pack's encoder alone on the
packed file's level-0 bytes (`format_writer_raw_bench`, 2 threads) and `zstd -3 -T2` of those raw
bytes, interleaved; then the encoder against zstd on those slices fed 1, 2 and 4 times over
(encoder_depth). For every N: `vispack-run --force --threads 2`, then the
pack stage and the OpenVDB export alone, each under `/usr/bin/time -v` (peak resident memory).
"""
import json
import os
import re
import subprocess
import sys

from common import median, write_json

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "python"))
import vispack  # noqa: E402  (the project's own reader: the packed file's geometry)
from time_v import run_time_v  # noqa: E402

BIN = os.environ["VISPACK_BENCH_BIN"]
WORK = os.environ["VISPACK_BENCH_WORK"]
REPS = int(os.environ.get("VISPACK_BENCH_REAL_REPS", "3"))


def time_v(cmd, log, **kw):
    """Runs cmd under /usr/bin/time -v; returns wall s, CPU s (user + system), peak RSS MiB."""
    t = run_time_v(cmd, log, **kw)
    return t["wall_s"], t["cpu_s"], t["peak_rss_mib"]


def stage_seconds(stdout):
    """Per-stage seconds from vispack-run's summary lines ("STAGE: ran (..., S s) -> OUT")."""
    out = {}
    for line in stdout.splitlines():
        m = re.match(r"^([\w+-]+): .*?([0-9.]+(?:e[+-]?\d+)?) s\)", line)
        if m:
            out[m.group(1)] = float(m.group(2))
    return out


def make_stack(base, n, dest):
    """A stack of n slices linked from base's slices in ping-pong order (see the docstring)."""
    cfg = json.load(open(os.path.join(base, "config.json")))
    dirs = {key: cfg[key]["dir"] for key in ("rgb", "ct", "seg") if key in cfg}
    files = {key: sorted(os.listdir(os.path.join(base, d))) for key, d in dirs.items()}
    count = len(files["rgb"])
    if os.path.exists(os.path.join(dest, ".complete")) and open(os.path.join(dest, ".complete")).read() == f"{base} {n}":
        return os.path.join(dest, "config.json")
    subprocess.run(["rm", "-rf", dest], check=True)
    os.makedirs(dest)
    for key, d in dirs.items():
        os.makedirs(os.path.join(dest, d))
        names = files[key]
        if len(names) != count:
            raise SystemExit(f"real_size: {base}/{d} holds {len(names)} files, rgb {count}")
        # The file names are the phantom's own (prefix + 4-digit number + extension).
        for k in range(n):
            p = k % (2 * count)
            src = names[p if p < count else 2 * count - 1 - p]
            name = re.sub(r"\d{4}", f"{k:04d}", src, count=1)
            os.symlink(os.path.join(base, d, src), os.path.join(dest, d, name))
    for extra in ("palette.json",):
        if os.path.exists(os.path.join(base, extra)):
            subprocess.run(["cp", os.path.join(base, extra), dest], check=True)
    cfg["name"] = f"{cfg.get('name', 'vhp')}-pingpong-{n}"
    json.dump(cfg, open(os.path.join(dest, "config.json"), "w"), indent=1)
    open(os.path.join(dest, ".complete"), "w").write(f"{base} {n}")
    return os.path.join(dest, "config.json")


def level0_raw(vpk, path):
    """The packed file's level-0 voxels of every channel, raw, one after the other; returns the
    per-channel NRRDs `vispack-extract` wrote (the caller removes them)."""
    nrrds = []
    with open(path, "wb") as raw:
        for ch in ("rgba", "ct", "labels"):
            nrrd = path + "." + ch + ".nrrd"
            subprocess.run([f"{BIN}/vispack-extract", vpk, "--channel", ch, "-o", nrrd], check=True,
                           stdout=subprocess.DEVNULL)
            with open(nrrd, "rb") as f:
                data = f.read()
            raw.write(data[data.index(b"\n\n") + 2:])
            nrrds.append(nrrd)
    return nrrds


def write_repeated(nrrds, path, repeat):
    """Each NRRD's raw data `repeat` times over, the channels one after the other: the level-0
    bytes of the stack `format_writer_raw_bench --repeat` feeds."""
    with open(path, "wb") as out:
        for nrrd in nrrds:
            with open(nrrd, "rb") as f:
                head = f.read(1 << 16)
                start = head.index(b"\n\n") + 2
            for _ in range(repeat):
                with open(nrrd, "rb") as f:
                    f.seek(start)
                    while True:
                        block = f.read(1 << 24)
                        if not block:
                            break
                        out.write(block)


def encoder_depth(vpk, raw, nrrds):
    """The pack's encoder against `zstd -3 -T2` as the stack deepens: the smallest stack's
    level-0 slices fed 1, 2 and 4 times over (`format_writer_raw_bench --repeat R`: 128, 256, 512
    slices' worth), against zstd of the same bytes (each channel's R copies one after the other),
    zstd's input read into the page cache first; interleaved, REPS rounds. The Writer's one-row
    slab is fresh memory on its first fill (page faults, paid once per run): the deeper stacks
    show the encoder past it, as it runs on a real stack of hundreds of slices."""
    rows = []
    for repeat in (1, 2, 4):
        raw_r = raw if repeat == 1 else f"{raw}.x{repeat}"
        if repeat > 1:
            write_repeated(nrrds, raw_r, repeat)
        row = {"repeat": repeat, "raw_bytes": os.path.getsize(raw_r), "writer": [], "zstd": []}
        for rep in range(REPS):
            proc = subprocess.run([f"{BIN}/format_writer_raw_bench", vpk, raw + ".vpk"] + nrrds
                                  + ["--threads", "2", "--repeat", str(repeat)],
                                  check=True, capture_output=True, text=True)
            row["writer"].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            row["vpk_bytes"] = os.path.getsize(raw + ".vpk")
            os.remove(raw + ".vpk")
            subprocess.run(["cat", raw_r], check=True, stdout=subprocess.DEVNULL)
            wall, cpu, rss = time_v(["zstd", "-3", "-T2", "-q", "-f", raw_r, "-o", raw_r + ".zst"],
                                    os.path.join(WORK, "real-size", f"zstd-x{repeat}-{rep}.time"))
            row["zstd"].append({"wall_s": wall, "cpu_s": cpu})
            row["zstd_bytes"] = os.path.getsize(raw_r + ".zst")
            os.remove(raw_r + ".zst")
            print(f"real_size: encoder x{repeat}: {row['writer'][-1]['write_s']:.2f} s, zstd {wall:.2f} s",
                  file=sys.stderr)
        if repeat > 1:
            os.remove(raw_r)
        rows.append(row)
    return rows


def main():
    base, out = os.path.abspath(sys.argv[1]), sys.argv[2]
    counts = sorted(int(s) for s in sys.argv[3:])
    logs = os.path.join(WORK, "real-size")
    os.makedirs(logs, exist_ok=True)
    load = lambda: [float(x) for x in open("/proc/loadavg").read().split()[:3]]  # noqa: E731
    result = {"base": os.path.basename(base), "counts": counts, "reps": REPS, "runs": [], "memory": [],
              "load_at_start": load()}
    for n in counts:
        config = make_stack(base, n, os.path.join(WORK, "data", f"real-{n}"))
        folder = os.path.dirname(config)
        if n == counts[0]:
            # One and two threads, interleaved round by round.
            for rep in range(REPS):
                for threads in (1, 2):
                    log = os.path.join(logs, f"run-{n}-t{threads}-{rep}")
                    with open(log + ".out", "w") as so:
                        wall, cpu, rss = time_v([f"{BIN}/vispack-run", config, "--force", "--threads", str(threads)],
                                                log + ".time", stdout=so, stderr=subprocess.DEVNULL)
                    result["runs"].append({"slices": n, "threads": threads, "rep": rep, "wall_s": wall, "cpu_s": cpu,
                                           "peak_rss_mib": rss, "load": load(),
                                           "stages_s": stage_seconds(open(log + ".out").read())})
                    print(f"real_size: {n} slices, {threads} thread(s): {wall:.1f} s wall, {cpu:.1f} s CPU",
                          file=sys.stderr)
            # The pack stage against zstd -3 -T2 of the same level-0 bytes, interleaved.
            vpk = json.load(open(os.path.join(folder, "work", "pack", "report.json")))["output"]
            raw = os.path.join(logs, "level0.raw")
            nrrds = level0_raw(vpk, raw)
            pack, zstd, writer = [], [], []
            for rep in range(REPS):
                # The encoder alone (format::Writer with the file's options) on the same bytes,
                # read into memory first (its reading timed apart): the same work as zstd's.
                proc = subprocess.run([f"{BIN}/format_writer_raw_bench", vpk, raw + ".vpk"] + nrrds
                                      + ["--threads", "2"], check=True, capture_output=True, text=True)
                writer.append(json.loads(proc.stdout.strip().splitlines()[-1]))
                os.remove(raw + ".vpk")
                log = os.path.join(logs, f"pack-{n}-{rep}.time")
                wall, cpu, rss = time_v([f"{BIN}/vispack-pack", "--config", config, "--force", "--quiet",
                                         "--threads", "2"], log, stdout=subprocess.DEVNULL)
                rep_json = json.load(open(os.path.join(folder, "work", "pack", "report.json")))
                pack.append({"wall_s": wall, "cpu_s": cpu, "stage_s": rep_json["seconds"], "peak_rss_mib": rss})
                wall, cpu, rss = time_v(["zstd", "-3", "-T2", "-q", "-f", raw, "-o", raw + ".zst"],
                                        os.path.join(logs, f"zstd-{rep}.time"))
                zstd.append({"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": rss})
            result["pack_vs_zstd"] = {"slices": n, "pack": pack, "zstd": zstd,
                                      "raw_bytes": os.path.getsize(raw), "zstd_bytes": os.path.getsize(raw + ".zst"),
                                      "vpk_bytes": os.path.getsize(vpk),
                                      "pack_wall_s": median([p["wall_s"] for p in pack]),
                                      "pack_stage_s": median([p["stage_s"] for p in pack]),
                                      "zstd_wall_s": median([z["wall_s"] for z in zstd]),
                                      "writer": writer,
                                      "writer_wall_s": median([x["write_s"] for x in writer]),
                                      "writer_cpu_s": median([x["write_cpu_s"] for x in writer]),
                                      "zstd_cpu_s": median([z["cpu_s"] for z in zstd])}
            result["encoder_depth"] = encoder_depth(vpk, raw, nrrds)
            for path in nrrds + [raw, raw + ".zst"]:
                if os.path.exists(path):  # encoder_depth removed its zstd output
                    os.remove(path)
        else:
            log = os.path.join(logs, f"run-{n}-t2")
            with open(log + ".out", "w") as so:
                wall, cpu, rss = time_v([f"{BIN}/vispack-run", config, "--force", "--threads", "2"], log + ".time",
                                        stdout=so, stderr=subprocess.DEVNULL)
            result["runs"].append({"slices": n, "threads": 2, "rep": 0, "wall_s": wall, "cpu_s": cpu, "peak_rss_mib": rss,
                                   "load": load(), "stages_s": stage_seconds(open(log + ".out").read())})
            print(f"real_size: {n} slices, 2 threads: {wall:.1f} s wall, {cpu:.1f} s CPU, {rss:.0f} MiB", file=sys.stderr)
        mem = {"slices": n, "run_peak_rss_mib": max(r["peak_rss_mib"] for r in result["runs"] if r["slices"] == n)}
        for stage in ("pack", "vdb"):
            if stage == "vdb" and not json.load(open(config)).get("vdb", {}).get("enabled", False):
                continue
            wall, cpu, rss = time_v([f"{BIN}/vispack-{stage}", "--config", config, "--force", "--quiet", "--threads", "2"],
                                    os.path.join(logs, f"{stage}-{n}-mem.time"), stdout=subprocess.DEVNULL)
            mem[f"{stage}_peak_rss_mib"] = rss
            mem[f"{stage}_wall_s"] = wall
            report = json.load(open(os.path.join(folder, "work", stage, "report.json")))
            mem[f"{stage}_report"] = {k: report[k] for k in ("output_bytes", "level", "chosen_level", "seconds",
                                                             "layout", "layout_reason")
                                      if k in report}
            if "parts" in report:  # the OpenVDB export written as parts (vdb.layout "auto")
                mem[f"{stage}_report"]["parts"] = len(report["parts"])
        # One level-0 brick row of the output: x * y * brick_edge voxels of every stored channel.
        vpk = json.load(open(os.path.join(folder, "work", "pack", "report.json")))["output"]
        with vispack.open(vpk) as v:
            level0 = v.levels[0]
            mem["dims"] = list(level0.dims)
            mem["brick_edge"] = v.brick_edge
            mem["bytes_per_voxel"] = sum(c.brick_bytes_per_voxel for c in v.channel_infos)
            mem["brick_row_mib"] = (level0.dims[0] * level0.dims[1] * v.brick_edge * mem["bytes_per_voxel"]
                                    / 2**20)
        result["memory"].append(mem)
        print(f"real_size: {n} slices: memory {mem}", file=sys.stderr)
        # Keep the smallest stack's folder (its work folder is measured above); the others are big.
        if n != counts[0]:
            subprocess.run(["rm", "-rf", os.path.join(folder, "work"), os.path.join(folder, "out")], check=True)
    write_json(out, result)


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""Pack stage sweep (brick edge x zstd level) on a phantom whose pipeline has run, beside plain
`zstd -T2` of the same raw voxels, vispack's own OpenVDB export and gzip-compressed NRRDs, all
run round-robin (every setting and peer once per repetition), medians.
Usage: pack_sweep.py PHANTOM_DIR OUT_JSON"""
import json
import os
import subprocess
import sys

from common import QUICK, median, timed2, write_json

BIN = os.environ["VISPACK_BENCH_BIN"]
WORK = os.environ["VISPACK_BENCH_WORK"]


def absolute_config(phantom, changes, out_dir, name):
    """A copy of the phantom's config with absolute paths, `changes` merged into "pack"."""
    cfg = json.load(open(os.path.join(phantom, "config.json")))
    base = os.path.abspath(phantom)

    def a(p):
        return p if os.path.isabs(p) else os.path.join(base, p)

    cfg["work_dir"] = a(cfg.get("work_dir", "work"))
    cfg["output"] = os.path.join(out_dir, name + ".vpk")
    cfg["vdb_output"] = os.path.join(out_dir, name + ".vdb")
    for sec in ("rgb", "ct", "seg"):
        if cfg.get(sec):
            cfg[sec]["dir"] = a(cfg[sec]["dir"])
            if "palette" in cfg[sec]:
                cfg[sec]["palette"] = a(cfg[sec]["palette"])
    cfg["pack"].update(changes)
    path = os.path.join(out_dir, name + ".json")
    json.dump(cfg, open(path, "w"), indent=1)
    return path, cfg


def nrrd_split(path):
    data = open(path, "rb").read()
    i = data.index(b"\n\n") + 2
    return data[:i], data[i:]


def main():
    phantom, out = sys.argv[1:3]
    sweep = os.path.join(WORK, "pack-sweep")
    os.makedirs(sweep, exist_ok=True)
    reps = 1 if QUICK else 3
    edges = [32, 64] if QUICK else [32, 64, 128]
    levels = [1, 3] if QUICK else [1, 3, 9, 19]
    # Set-up, untimed: the default setting's file is the reference volume for the peers; its
    # level-0 raw voxels as vispack-extract writes them (rgba8, int16 HU, labels), one payload
    # file per channel for gzip and all three concatenated for zstd.
    cfg_path, cfg = absolute_config(phantom, {"threads": 2}, sweep, "default")
    subprocess.run([f"{BIN}/vispack-pack", "--config", cfg_path, "--force", "--quiet"], check=True,
                   stdout=subprocess.DEVNULL)
    vpk = cfg["output"]
    raw_path = os.path.join(sweep, "level0.raw")
    channels, headers = {}, {}
    with open(raw_path, "wb") as raw:
        for ch in ("rgba", "ct", "labels"):
            nrrd = os.path.join(sweep, ch + ".nrrd")
            subprocess.run([f"{BIN}/vispack-extract", vpk, "--channel", ch, "-o", nrrd], check=True,
                           stdout=subprocess.DEVNULL)
            header, payload = nrrd_split(nrrd)
            raw.write(payload)
            channels[ch] = len(payload)
            headers[ch] = header
            open(os.path.join(sweep, ch + ".payload"), "wb").write(payload)
    raw_bytes = sum(channels.values())
    # Every measured command, run round-robin: each repetition runs every vispack setting and
    # every peer once (A B C ... A B C ...), so all see the same machine load; medians over the
    # repetitions.
    runs = {}
    for edge in edges:
        for level in levels:
            path, _ = absolute_config(phantom, {"brick_edge": edge, "zstd_level": level,
                                                "threads": 2}, sweep, f"e{edge}_z{level}")
            runs[("pack", edge, level)] = [f"{BIN}/vispack-pack", "--config", path, "--force",
                                           "--quiet", "--threads", "2"]
    for level in levels:
        runs[("zstd", level)] = ["zstd", f"-{level}", "-T2", "-q", "-f", raw_path, "-o",
                                 raw_path + ".zst"]
    # gzip-compressed NRRD: the same header with "encoding: gzip" and the payload gzipped
    # (gzip -6, what NRRD writers such as ITK and pynrrd use by default); one command per channel.
    for ch in channels:
        pl = os.path.join(sweep, ch + ".payload")
        runs[("gzip", ch)] = ["sh", "-c", f"gzip -6 -c '{pl}' > '{pl}.gz'"]
    vdb_cfg, vcfg = absolute_config(phantom, {}, sweep, "default")
    runs[("vdb",)] = [f"{BIN}/vispack-vdb", "--config", vdb_cfg, "--force", "--quiet", "--threads", "2"]
    timing = {k: [] for k in runs}
    sizes = {}
    for _ in range(reps):
        for key, cmd in runs.items():
            timing[key].append(timed2(cmd, stdout=subprocess.DEVNULL))
            if key[0] == "zstd":
                sizes[key] = os.path.getsize(raw_path + ".zst")
            elif key[0] == "pack":
                sizes[key] = os.path.getsize(os.path.join(sweep, f"e{key[1]}_z{key[2]}.vpk"))

    def wall(key):
        return [t for t, _ in timing[key]]

    def cpu(key):
        return median([c for _, c in timing[key]])

    rows = []
    for edge in edges:
        for level in levels:
            k = ("pack", edge, level)
            rows.append({"brick_edge": edge, "zstd_level": level, "seconds": median(wall(k)),
                         "cpu_seconds": cpu(k), "times": wall(k), "bytes": sizes[k]})
            print(f"pack e{edge}_z{level}: {median(wall(k)):.2f} s, {sizes[k] / 1e6:.2f} MB", file=sys.stderr)
    zstd_rows = [{"zstd_level": level, "seconds": median(wall(("zstd", level))), "times": wall(("zstd", level)),
                  "cpu_seconds": cpu(("zstd", level)), "bytes": sizes[("zstd", level)]} for level in levels]
    gz = {"bytes": 0, "seconds": 0.0, "cpu_seconds": 0.0}
    for ch in channels:
        pl = os.path.join(sweep, ch + ".payload")
        gz_file = os.path.join(sweep, ch + ".gz.nrrd")
        with open(gz_file, "wb") as f:
            f.write(headers[ch].replace(b"encoding: raw", b"encoding: gzip"))
            f.write(open(pl + ".gz", "rb").read())
        gz["bytes"] += os.path.getsize(gz_file)
        gz["seconds"] += median(wall(("gzip", ch)))
        gz["cpu_seconds"] += cpu(("gzip", ch))
        os.remove(pl)
        os.remove(pl + ".gz")
    os.remove(raw_path + ".zst")
    vdb = {"seconds": median(wall(("vdb",))), "cpu_seconds": cpu(("vdb",)),
           "bytes": os.path.getsize(vcfg["vdb_output"])}
    info = json.load(open(os.path.join(phantom, "truth", "transforms.json")))
    write_json(out, {"phantom": os.path.basename(os.path.abspath(phantom)), "preset": info.get("preset"),
                     "raw_bytes": raw_bytes, "channels": channels, "reps": reps, "rows": rows,
                     "zstd": zstd_rows, "gzip_nrrd": gz, "vdb": vdb, "interleaved": True,
                     "default_bytes": os.path.getsize(vpk)})
    os.remove(raw_path)


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""Pack stage sweep (brick edge x zstd level) on a phantom whose pipeline has run, beside plain
`zstd -T2` of the same raw voxels, the OpenVDB export and gzip-compressed NRRDs.
Usage: pack_sweep.py PHANTOM_DIR OUT_JSON"""
import json
import os
import subprocess
import sys

from common import QUICK, median, timed, timed2, write_json

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
    rows = []
    for edge in edges:
        for level in levels:
            name = f"e{edge}_z{level}"
            cfg_path, cfg = absolute_config(phantom, {"brick_edge": edge, "zstd_level": level,
                                                      "threads": 2}, sweep, name)
            tc = [timed2([f"{BIN}/vispack-pack", "--config", cfg_path, "--force", "--quiet",
                          "--threads", "2"], stdout=subprocess.DEVNULL) for _ in range(reps)]
            times = [t for t, _ in tc]
            rows.append({"brick_edge": edge, "zstd_level": level, "seconds": median(times),
                         "cpu_seconds": median([c for _, c in tc]),
                         "times": times, "bytes": os.path.getsize(cfg["output"])})
            print(f"pack {name}: {median(times):.2f} s, {rows[-1]['bytes'] / 1e6:.2f} MB", file=sys.stderr)
    # The default setting's file is the reference volume for the peers.
    cfg_path, cfg = absolute_config(phantom, {"threads": 2}, sweep, "default")
    subprocess.run([f"{BIN}/vispack-pack", "--config", cfg_path, "--force", "--quiet"], check=True,
                   stdout=subprocess.DEVNULL)
    vpk = cfg["output"]
    # Raw level-0 voxels, as vispack-extract writes them (rgba8, int16 HU, labels).
    raw_path = os.path.join(sweep, "level0.raw")
    raw_bytes = 0
    gz = {"bytes": 0, "seconds": 0.0}
    channels = {}
    with open(raw_path, "wb") as raw:
        for ch in ("rgba", "ct", "labels"):
            nrrd = os.path.join(sweep, ch + ".nrrd")
            subprocess.run([f"{BIN}/vispack-extract", vpk, "--channel", ch, "-o", nrrd], check=True,
                           stdout=subprocess.DEVNULL)
            header, payload = nrrd_split(nrrd)
            raw.write(payload)
            raw_bytes += len(payload)
            channels[ch] = len(payload)
            # gzip-compressed NRRD: the same header with "encoding: gzip" and the payload gzipped
            # (gzip -6, what NRRD writers such as ITK and pynrrd use by default).
            payload_path = os.path.join(sweep, ch + ".payload")
            open(payload_path, "wb").write(payload)
            gz_times, gz_cpu = [], []
            for _ in range(reps):
                t, c = timed2(["sh", "-c", f"gzip -6 -c '{payload_path}' > '{payload_path}.gz'"])
                gz_times.append(t)
                gz_cpu.append(c)
            header = header.replace(b"encoding: raw", b"encoding: gzip")
            gz_file = os.path.join(sweep, ch + ".gz.nrrd")
            with open(gz_file, "wb") as f:
                f.write(header)
                f.write(open(payload_path + ".gz", "rb").read())
            gz["bytes"] += os.path.getsize(gz_file)
            gz["seconds"] += median(gz_times)
            gz["cpu_seconds"] = gz.get("cpu_seconds", 0.0) + median(gz_cpu)
            os.remove(payload_path)
            os.remove(payload_path + ".gz")
    zstd_rows = []
    for level in levels:
        tc = [timed2(["zstd", f"-{level}", "-T2", "-q", "-f", raw_path, "-o", raw_path + ".zst"])
              for _ in range(reps)]
        times = [t for t, _ in tc]
        zstd_rows.append({"zstd_level": level, "seconds": median(times), "times": times,
                          "cpu_seconds": median([c for _, c in tc]),
                          "bytes": os.path.getsize(raw_path + ".zst")})
    os.remove(raw_path + ".zst")
    vdb_cfg, cfg = absolute_config(phantom, {}, sweep, "default")
    tc = [timed2([f"{BIN}/vispack-vdb", "--config", vdb_cfg, "--force", "--quiet", "--threads", "2"],
                 stdout=subprocess.DEVNULL) for _ in range(reps)]
    vdb = {"seconds": median([t for t, _ in tc]), "cpu_seconds": median([c for _, c in tc]),
           "bytes": os.path.getsize(cfg["vdb_output"])}
    info = json.load(open(os.path.join(phantom, "truth", "transforms.json")))
    write_json(out, {"phantom": os.path.basename(os.path.abspath(phantom)), "preset": info.get("preset"),
                     "raw_bytes": raw_bytes, "channels": channels, "reps": reps, "rows": rows,
                     "zstd": zstd_rows, "gzip_nrrd": gz, "vdb": vdb,
                     "default_bytes": os.path.getsize(vpk)})
    os.remove(raw_path)


if __name__ == "__main__":
    main()

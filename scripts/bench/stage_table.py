#!/usr/bin/python3
"""The stage table: each stage executable's time per slice on one and on two threads, with its
error against the phantom's truth, and `zstd -3 -T2` of the same raw bytes as the pack peer
(run interleaved with three more two-thread pack runs).
Usage: stage_table.py PHANTOM_DIR OUT_JSON
Runs `vispack-STAGE --config C --force --quiet --threads T` (T = 1, then 2) for every stage under
`/usr/bin/time -v` and reads the stage's own time from work/STAGE/report.json."""
import json
import os
import subprocess
import sys

import numpy as np
from PIL import Image

from common import median, pair_error_px, point_error_px, rms, timed2, write_json
from time_v import read_time_v

BIN = os.environ["VISPACK_BENCH_BIN"]
WORK = os.environ["VISPACK_BENCH_WORK"]
STAGES = ["register", "mask", "labels", "pack", "vdb"]


def read_nrrd(path):
    """A raw-encoded NRRD written by vispack (x fastest) as a numpy array (z, y, x[, c])."""
    data = open(path, "rb").read()
    i = data.index(b"\n\n")
    fields = dict(l.split(": ", 1) for l in data[:i].decode().splitlines()[1:] if ": " in l)
    dtype = {"uint8": np.uint8, "uint16": np.uint16, "int16": np.int16, "float": np.float32}[fields["type"]]
    sizes = [int(s) for s in fields["sizes"].split()]
    return np.frombuffer(data[i + 2:], dtype=dtype).reshape(sizes[::-1])


def affine(s, centre):
    """2x3 map of a transforms.json slice entry: rotation about the centre, then the shift."""
    a = np.deg2rad(s["rotation_deg"])
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    c = np.asarray(centre, float)
    t = c - r @ c + [s["dx_px"], s["dy_px"]]
    return np.hstack([r, t[:, None]])


def peak_rss_mib(log):
    return read_time_v(log)["peak_rss_mib"]


def run_stage(stage, config, threads, log):
    wall, cpu = timed2(["/usr/bin/time", "-v", "-o", log, f"{BIN}/vispack-{stage}", "--config", config,
                        "--force", "--quiet", "--threads", str(threads)], stdout=subprocess.DEVNULL)
    return wall, cpu, peak_rss_mib(log)


def errors(phantom, truth, compared):
    """The stages' errors against truth, over the slices that can agree with it."""
    work = os.path.join(phantom, "work")
    w, h, centre = truth["width"], truth["height"], truth["center_px"]
    est = json.load(open(os.path.join(work, "register", "transforms.json")))["slices"]
    drift = [pair_error_px(affine(est[z], centre), affine(truth["slices"][z], centre), w, h)
             for z in compared if z != truth.get("reference_slice", 0)]
    # The same error at the image centre alone (no lever arm from a rotation error): the pixel
    # ((width - 1) / 2, (height - 1) / 2), not the frame's corner.
    mid = ((w - 1) / 2.0, (h - 1) / 2.0)
    centre_err = [point_error_px(affine(est[z], centre), affine(truth["slices"][z], centre), mid)
                  for z in compared if z != truth.get("reference_slice", 0)]
    t_mask = read_nrrd(os.path.join(phantom, "truth", "mask.nrrd")) != 0
    t_lab = read_nrrd(os.path.join(phantom, "truth", "labels.nrrd"))
    inter = union = lab_n = lab_eq = 0
    for z in compared:
        m = np.asarray(Image.open(os.path.join(work, "mask", f"mask_{z:04d}.png"))) >= 128
        inter += int(np.count_nonzero(m & t_mask[z]))
        union += int(np.count_nonzero(m | t_mask[z]))
        lab = np.asarray(Image.open(os.path.join(work, "labels", f"labels_{z:04d}.png"))).astype(np.int64)
        t = t_lab[z].astype(np.int64)
        # Away from edges: the truth label is uniform over the 3x3 neighbourhood (as test_truth).
        p = np.pad(t, 1, mode="edge")
        inner = np.ones_like(t, bool)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                inner &= p[dy:dy + t.shape[0], dx:dx + t.shape[1]] == t
        sel = inner & t_mask[z]
        lab_n += int(np.count_nonzero(sel))
        lab_eq += int(np.count_nonzero(lab[sel] == t[sel]))
    return {"drift_rms_px": rms(drift) if drift else 0.0, "drift_max_px": max(drift) if drift else 0.0,
            "drift_px": drift, "drift_centre_rms_px": rms(centre_err) if centre_err else 0.0, "iou": inter / union if union else 0.0,
            "labels_equal_pct": 100.0 * lab_eq / lab_n if lab_n else 0.0, "labels_compared": lab_n}


def main():
    phantom, out = sys.argv[1:3]
    phantom = os.path.abspath(phantom)
    config = os.path.join(phantom, "config.json")
    truth = json.load(open(os.path.join(phantom, "truth", "transforms.json")))
    n = len(truth["slices"])
    # Black and duplicated slices cannot agree with truth (no content / the previous anatomy).
    compared = [z for z, s in enumerate(truth["slices"]) if not s["black"] and s["duplicate_of"] is None]
    logs = os.path.join(WORK, "stage-table")
    os.makedirs(logs, exist_ok=True)
    runs = []
    for threads in (1, 2):
        for stage in STAGES:
            wall, cpu, rss = run_stage(stage, config, threads, os.path.join(logs, f"{stage}-t{threads}.time"))
            rep = json.load(open(os.path.join(phantom, "work", stage, "report.json")))
            runs.append({"stage": stage, "threads": threads, "stage_seconds": rep["seconds"],
                         "process_seconds": wall, "cpu_seconds": cpu, "peak_rss_mib": rss,
                         "output_bytes": rep.get("output_bytes"), "input_bytes": rep.get("input_bytes")})
            print(f"stage {stage} threads {threads}: {rep['seconds']:.2f} s", file=sys.stderr)
        err = errors(phantom, truth, compared)
        for r in runs:
            if r["threads"] == threads:
                r.update(err)
    # Peer for pack: `zstd -3 -T2` of the same level-0 raw voxels (rgba8, int16 HU, labels).
    vpk = json.load(open(os.path.join(phantom, "work", "pack", "report.json")))["output"]
    raw_path = os.path.join(logs, "level0.raw")
    with open(raw_path, "wb") as raw:
        for ch in ("rgba", "ct", "labels"):
            nrrd = os.path.join(logs, ch + ".nrrd")
            subprocess.run([f"{BIN}/vispack-extract", vpk, "--channel", ch, "-o", nrrd], check=True,
                           stdout=subprocess.DEVNULL)
            data = open(nrrd, "rb").read()
            raw.write(data[data.index(b"\n\n") + 2:])
            os.remove(nrrd)
    # Interleaved: the pack stage on two threads and `zstd -3 -T2` alternate, three times each
    # (pack, zstd, pack, zstd, ...), so that both see the same load; medians.
    tc, pack_s = [], []
    for _ in range(3):
        run_stage("pack", config, 2, os.path.join(logs, "pack-t2-vs-zstd.time"))
        pack_s.append(json.load(open(os.path.join(phantom, "work", "pack", "report.json")))["seconds"])
        tc.append(timed2(["zstd", "-3", "-T2", "-q", "-f", raw_path, "-o", raw_path + ".zst"]))
    zstd = {"seconds": median([t for t, _ in tc]), "cpu_seconds": median([c for _, c in tc]),
            "bytes": os.path.getsize(raw_path + ".zst"), "raw_bytes": os.path.getsize(raw_path),
            "interleaved_pack_seconds": pack_s, "pack_seconds": median(pack_s)}
    os.remove(raw_path)
    os.remove(raw_path + ".zst")
    write_json(out, {"phantom": os.path.basename(phantom), "preset": truth.get("preset"),
                     "width": truth["width"], "height": truth["height"], "slices": n,
                     "compared_slices": compared, "runs": runs, "zstd3_t2": zstd})


if __name__ == "__main__":
    main()

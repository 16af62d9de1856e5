#!/usr/bin/python3
"""vispack's slice renderer against VTK's GPU ray caster, interleaved: round by round,
one viewer_bench process (whole level 0, every --spv, median of FRAMES frames per row) then one
vtk_peer.py process (every sample distance, median of FRAMES frames), REPS rounds (A B A B ...).
Each row's frame time is the median over the rounds of the per-process medians; the PSNRs come from
the first round (both renderers are deterministic: the driver checks that every round gives the
same foreground PSNR to 0.01 dB and fails otherwise). Quality is each renderer's foreground PSNR
against its own fine reference (vispack: its CPU reference ray caster at 8 steps per voxel; VTK:
its own frame at sample distance 0.125 voxel). Writes VIEWER_JSON and VTK_JSON in the formats of
viewer_bench --json and vtk_peer.py, with "rounds" and the per-round times added.
Usage: viewer_peers.py BIN VPK SIZE SPV REPS FRAMES RES_DIR WORK_DIR"""
import copy
import json
import os
import shutil
import subprocess
import sys

from common import median, write_json

HERE = os.path.dirname(os.path.abspath(__file__))


def run(cmd, log):
    with open(log, "a") as f:
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        subprocess.run(cmd, check=True, stdout=f, stderr=subprocess.STDOUT)


def merge(runs, key_fields):
    """Median ms over the rounds, row by row (rows matched by key_fields); PSNR of round 0."""
    out = copy.deepcopy(runs[0])
    for i, row in enumerate(out["rows"]):
        key = tuple(row[k] for k in key_fields)
        per_round = []
        for r in runs:
            match = [x for x in r["rows"] if tuple(x[k] for k in key_fields) == key]
            if len(match) != 1:
                raise SystemExit(f"viewer_peers: row {key} missing or repeated in a round")
            m = match[0]
            if row["psnr_db"] is not None and m["psnr_db"] is not None and abs(m["psnr_db"] - row["psnr_db"]) > 0.01:
                raise SystemExit(f"viewer_peers: row {key}: PSNR differs between rounds "
                                 f"({row['psnr_db']} against {m['psnr_db']})")
            per_round.append(m["ms"])
        row["ms"] = median(per_round)
        row["ms_per_round"] = per_round
    out["rounds"] = len(runs)
    return out


def main():
    bin_dir, vpk, size, spv, reps, frames, res, work = sys.argv[1:9]
    reps, frames = int(reps), int(frames)
    log = os.path.join(res, "viewer.log")
    nrrd = os.path.join(work, "viewer_rgba.nrrd")
    run([os.path.join(bin_dir, "vispack-extract"), vpk, "--channel", "rgba", "-o", nrrd], log)
    vtk_cmd = ["/usr/bin/python3", os.path.join(HERE, "vtk_peer.py")]
    # VTK's offscreen window still needs an X display here (Mesa through GLX): Xvfb without one.
    if not os.environ.get("DISPLAY") and shutil.which("xvfb-run"):
        vtk_cmd = ["xvfb-run", "-a"] + vtk_cmd
    ref_png = os.path.join(res, "viewer_ref.png")
    ours, theirs = [], []
    for r in range(reps):
        vj = os.path.join(work, f"viewer-round{r}.json")
        kj = os.path.join(work, f"viewer_vtk-round{r}.json")
        cmd = [os.path.join(bin_dir, "viewer_bench"), "--file", vpk, "--size", str(size), "--spv", spv,
               "--reps", str(frames), "--json", vj]
        # The brick-paged measurements (not compared with VTK) in the first round only.
        cmd += ["--ref-png", ref_png] if r == 0 else ["--no-paged"]
        run(cmd, log)
        ours.append(json.load(open(vj)))
        run(vtk_cmd + [vj, nrrd, kj, "--reps", str(frames), "--ref-png", ref_png], log)
        theirs.append(json.load(open(kj)))
        print(f"viewer round {r + 1}/{reps} done", file=sys.stderr)
    write_json(os.path.join(res, "viewer.json"), merge(ours, ("mode", "level", "slices_per_voxel")))
    write_json(os.path.join(res, "viewer_vtk.json"), merge(theirs, ("sample_distance_voxels",)))


if __name__ == "__main__":
    main()

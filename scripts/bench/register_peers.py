#!/usr/bin/python3
"""Registration, vispack against elastix, interleaved: REPS rounds, each running register_bench
once (every vispack setting, every pair) and then elastix once per setting and pair, so both see
the same machine load; medians over all rounds. elastix's fixed cost per run (process start,
parameter parsing, result files; scripts/bench/elastix_peer.py fixed_cost) is measured once per
round too, so that the report can compare the work of both with their file reading included and
the process start-up of neither.
Usage: register_peers.py REGISTER_BENCH PHANTOM PAIRS REPS DUMP_DIR REGISTER_JSON ELASTIX_JSON
Writes REGISTER_JSON in register_bench's format (times over the rounds) and ELASTIX_JSON in
elastix_peer.py's format plus the fixed cost."""
import json
import os
import subprocess
import sys

from common import median, pair_error_px, rms, write_json
from elastix_peer import fixed_cost, run_pair, settings, write_params

VISPACK_LISTS = ("times", "cpu_times", "read_times", "read_cpu_times")


def main():
    exe, phantom, pairs, reps, dump, reg_out, ela_out = sys.argv[1:8]
    reps = max(1, int(reps))
    reg, ela, fixed = None, {}, []
    for rnd in range(reps):
        part = os.path.join(dump, f"register-round{rnd}.json")
        cmd = [exe, "--phantom", phantom, "--pairs", pairs, "--reps", "1", "--json", part]
        if rnd == 0:
            cmd += ["--dump", dump]
        subprocess.run(cmd, check=True)
        got = json.load(open(part))
        if reg is None:
            reg = got
        else:
            for mine, new in zip(reg["results"], got["results"]):
                for key in VISPACK_LISTS:
                    mine[key] += new[key]
        w, h = reg["width"], reg["height"]
        for res, iters, samples in settings():
            pdir, pfile = write_params(dump, res, iters, samples)
            e = ela.setdefault((res, iters, samples), {"times": [], "cpu_times": [], "estimates": [], "errors_px": []})
            for i, pair in enumerate(reg["pairs"]):
                t, c, m = run_pair(pfile, os.path.join(dump, f"pair{i}_fixed.mhd"),
                                   os.path.join(dump, f"pair{i}_moving.mhd"), os.path.join(pdir, f"pair{i}"))
                e["times"].append(t)
                e["cpu_times"].append(c)
                if rnd == 0:
                    e["estimates"].append(m.tolist())
                    e["errors_px"].append(pair_error_px(m, pair["truth"], w, h))
        fixed.append(fixed_cost(dump, reps=1))
    for r in reg["results"]:
        r["seconds_per_pair"] = median(r["times"])
        r["cpu_seconds_per_pair"] = median(r["cpu_times"])
        r["read_seconds_per_pair"] = median(r["read_times"])
        r["read_cpu_seconds_per_pair"] = median(r["read_cpu_times"])
    reg["rounds"] = reps
    reg["interleaved"] = True
    write_json(reg_out, reg)
    results = []
    for (res, iters, samples), e in ela.items():
        results.append({"resolutions": res, "iterations": iters, "samples": samples,
                        "seconds_per_pair": median(e["times"]), "cpu_seconds_per_pair": median(e["cpu_times"]),
                        "times": e["times"], "cpu_times": e["cpu_times"], "errors_px": e["errors_px"],
                        "rms_px": rms(e["errors_px"]), "estimates": e["estimates"]})
        print(f"elastix r{res} i{iters}: {1e3 * results[-1]['seconds_per_pair']:.0f} ms/pair, "
              f"RMS {results[-1]['rms_px']:.3f} px", file=sys.stderr)
    write_json(ela_out, {"width": reg["width"], "height": reg["height"], "threads": 1, "rounds": reps,
                         "interleaved": True, "results": results,
                         "fixed_cost_seconds": median([t for t, _ in fixed]),
                         "fixed_cost_cpu_seconds": median([c for _, c in fixed]),
                         "fixed_cost_command": "elastix on a 16×16 pair, 1 resolution, 1 iteration"})


if __name__ == "__main__":
    main()

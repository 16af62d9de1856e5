#!/usr/bin/python3
"""The fixed cost of starting a vispack process (dynamic loading of OpenCV, OpenImageIO, OpenVDB,
TBB, static initialisation).

  startup.py OUT_JSON [REPS]
      `vispack-run --help` (loads everything, does no work) REPS times; writes the median wall
      and CPU seconds (the scaling fit subtracts them, scripts/bench/report.py).
  startup.py --per-exe OUT_JSON REPS BIN_DIR [BIN_DIR_B]
      Every vispack-* executable in BIN_DIR (and the same names in BIN_DIR_B, run interleaved
      A B A B, for a before/after): median CPU (user + sys) and wall ms of `EXE --help`, the
      libraries `ldd` lists (and whether OpenImageIO is among them), the loader's relocation
      count (LD_DEBUG=statistics) and the load average at the start. Prints a Markdown table."""
import os
import re
import subprocess
import sys

from common import median, timed2, write_json


def libraries(exe):
    """The shared libraries `ldd` lists for exe, one name a line."""
    out = subprocess.run(["ldd", exe], capture_output=True, text=True, check=True).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def relocations(exe):
    """The loader's relocations (symbol + relative) for one `EXE --help`."""
    env = dict(os.environ, LD_DEBUG="statistics")
    err = subprocess.run([exe, "--help"], capture_output=True, text=True, env=env).stderr
    total = 0
    for key in ("final number of relocations", "number of relative relocations"):
        m = re.findall(rf"{key}: (\d+)", err)
        if m:
            total += int(m[-1])
    return total


def per_exe(out, reps, dirs):
    load_average = list(os.getloadavg())
    names = sorted(n for n in os.listdir(dirs[0]) if n.startswith("vispack-"))
    rows = []
    for name in names:
        exes = [os.path.join(d, name) for d in dirs if os.path.exists(os.path.join(d, name))]
        samples = [[] for _ in exes]
        for _ in range(reps):
            for i, exe in enumerate(exes):  # interleaved: A B A B
                samples[i].append(timed2([exe, "--help"], stdout=subprocess.DEVNULL))
        row = {"exe": name, "versions": []}
        for exe, s in zip(exes, samples):
            libs = libraries(exe)
            row["versions"].append({"path": exe, "libraries": len(libs),
                                    "openimageio": any("libOpenImageIO" in x for x in libs),
                                    "relocations": relocations(exe),
                                    "cpu_ms": 1e3 * median([c for _, c in s]),
                                    "wall_ms": 1e3 * median([t for t, _ in s])})
        rows.append(row)
    write_json(out, {"command": "EXE --help", "reps": reps, "dirs": dirs, "rows": rows,
                     "load_average": load_average})
    cols = ["libraries", "relocations", "cpu_ms", "wall_ms"]
    head = ["executable"] + [f"{c} {chr(65 + i)}" for c in cols for i in range(len(dirs))]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        cells = [r["exe"]]
        for c in cols:
            for v in r["versions"]:
                cells.append(f"{v[c]:.0f}")
        print("| " + " | ".join(cells) + " |")


def main():
    if sys.argv[1] == "--per-exe":
        per_exe(sys.argv[2], int(sys.argv[3]), sys.argv[4:])
        return
    bin_dir = os.environ["VISPACK_BENCH_BIN"]
    out = sys.argv[1]
    reps = int(sys.argv[2]) if len(sys.argv) > 2 else 5
    cmd = [f"{bin_dir}/vispack-run", "--help"]
    tc = [timed2(cmd, stdout=subprocess.DEVNULL) for _ in range(reps)]
    write_json(out, {"command": "vispack-run --help", "reps": reps,
                     "seconds": median([t for t, _ in tc]), "cpu_seconds": median([c for _, c in tc]),
                     "times": [t for t, _ in tc], "cpu_times": [c for _, c in tc]})


if __name__ == "__main__":
    main()

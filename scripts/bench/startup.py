#!/usr/bin/python3
"""The fixed cost of starting a vispack process (dynamic loading of OpenCV, OpenVDB, TBB, static
initialisation): `vispack-run --help`, which loads everything and does no work, run REPS times.
Writes the median wall and CPU seconds; the scaling fit subtracts them (scripts/bench/report.py).
Usage: startup.py OUT_JSON [REPS]"""
import os
import subprocess
import sys

from common import median, timed2, write_json

BIN = os.environ["VISPACK_BENCH_BIN"]


def main():
    out = sys.argv[1]
    reps = int(sys.argv[2]) if len(sys.argv) > 2 else 5
    cmd = [f"{BIN}/vispack-run", "--help"]
    tc = [timed2(cmd, stdout=subprocess.DEVNULL) for _ in range(reps)]
    write_json(out, {"command": "vispack-run --help", "reps": reps,
                     "seconds": median([t for t, _ in tc]), "cpu_seconds": median([c for _, c in tc]),
                     "times": [t for t, _ in tc], "cpu_times": [c for _, c in tc]})


if __name__ == "__main__":
    main()

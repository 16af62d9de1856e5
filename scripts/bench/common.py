"""Shared helpers of the benchmark scripts (scripts/bench/*.py): timing and the pair error."""
import json
import os
import resource
import statistics
import subprocess
import time

import numpy as np

MODE = os.environ.get("VISPACK_BENCH_MODE", "full")
QUICK = MODE == "quick"


def timed(cmd, **kw):
    """Runs cmd (list), raising CalledProcessError on failure; returns the wall seconds."""
    return timed2(cmd, **kw)[0]


def timed2(cmd, **kw):
    """Runs cmd (list); returns (wall seconds, CPU seconds of the child: user + system). On this
    shared machine the CPU time is the steadier measure; the wall time includes waiting for a core."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, **kw)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def median(xs):
    return statistics.median(xs)


def pair_error_px(est, truth, width, height):
    """Largest displacement (px) between two 2x3 affine maps over the image corners and centre:
    the same measure as vispack's rigid_motion_px of the residual transform."""
    e = np.asarray(est, float)
    t = np.asarray(truth, float)
    pts = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1],
                    [(width - 1) / 2, (height - 1) / 2, 1]], float)
    d = pts @ e.T - pts @ t.T
    return float(np.max(np.hypot(d[:, 0], d[:, 1])))


def point_error_px(est, truth, point):
    """Displacement (px) between two 2x3 affine maps at one image point (x, y)."""
    p = np.array([point[0], point[1], 1.0])
    d = np.asarray(est, float) @ p - np.asarray(truth, float) @ p
    return float(np.hypot(d[0], d[1]))


def rms(xs):
    return float(np.sqrt(np.mean(np.square(xs))))


def write_json(path, obj):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)

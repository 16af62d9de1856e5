#!/usr/bin/python3
"""Prints the machine the benchmark runs on (cores, CPU model, memory, load, date) as JSON."""
import datetime
import json
import os
import platform
import subprocess


def cpu_model():
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def mem_gib():
    for line in open("/proc/meminfo"):
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) / 1024 / 1024
    return 0.0


def commit():
    try:
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        return subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def gl_renderer():
    return os.environ.get("VISPACK_BENCH_GL", "")


print(json.dumps({
    "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    "cores": os.cpu_count(),
    "cpu": cpu_model(),
    "memory_gib": round(mem_gib(), 1),
    "load_average": list(os.getloadavg()),
    "kernel": platform.release(),
    "commit": commit(),
    "mode": os.environ.get("VISPACK_BENCH_MODE", ""),
}, indent=1))

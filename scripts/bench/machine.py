#!/usr/bin/python3
"""Prints the machine the benchmark runs on (cores, CPU model, memory, load, date) and the source
tree it was built from (full commit, dirty flag and the changed paths) as JSON."""
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


ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# The report's own outputs: a previous run of scripts/bench.sh rewrites them, which does not make
# the measured code differ from the commit.
REPORT_OUTPUTS = ("docs/BENCHMARKS.md", "docs/img")


def git(*args):
    return subprocess.run(["git", "-C", ROOT, *args], capture_output=True, text=True,
                          check=True).stdout


def provenance():
    """{"commit": full hash, "commit_short", "dirty": bool, "dirty_paths": [...]}. Dirty = tracked
    files modified or staged, or untracked files that git does not ignore (new scripts count; build
    folders are ignored by .gitignore), leaving out the report's own outputs."""
    try:
        full = git("rev-parse", "HEAD").strip()
        status = git("status", "--porcelain", "--", ".", *(f":(exclude){p}" for p in REPORT_OUTPUTS))
    except (OSError, subprocess.CalledProcessError):
        return {"commit": "unknown", "commit_short": "unknown", "dirty": True,
                "dirty_paths": ["(not a git checkout: provenance unknown)"]}
    paths = [line[3:] for line in status.splitlines() if line.strip()]
    return {"commit": full, "commit_short": full[:12], "dirty": bool(paths), "dirty_paths": paths}


def gl_renderer():
    return os.environ.get("VISPACK_BENCH_GL", "")


def main():
    info = {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cores": os.cpu_count(),
        "cpu": cpu_model(),
        "memory_gib": round(mem_gib(), 1),
        "load_average": list(os.getloadavg()),
        "kernel": platform.release(),
        "mode": os.environ.get("VISPACK_BENCH_MODE", ""),
    }
    info.update(provenance())
    print(json.dumps(info, indent=1))


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""Peak resident memory of `vispack-vdb` under memory budgets and layouts (docs/BENCHMARKS.md
"OpenVDB export memory under a budget").

Usage: vdb_budget.py OUT_CSV ROUNDS DIR:LAYOUT:BUDGET...
  DIR     a phantom folder whose config.json has been run up to pack (its "output" exists)
  LAYOUT  vdb.layout: "file" (one file, the finest level within the budget) or "auto"
  BUDGET  vdb.max_memory_mb
Every setting runs once per round, ROUNDS rounds (interleaved), as `/usr/bin/time -v vispack-vdb
--config DIR/config_vdb_LAYOUT_BUDGET.json --force` (vdb.level "auto"; output out/vdb_*.vdb,
removed after each run). One CSV row per run: the level and layout chosen, the level's active
voxels and leaves, its mapped payload and estimate (report.json "estimates", MiB), the peak
RSS (MiB), CPU s (user + system) and the bytes written. Env: VISPACK_BIN (default build/bin).
"""
import csv
import json
import os
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from time_v import run_time_v  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
BIN = os.environ.get("VISPACK_BIN", os.path.join(ROOT, "build", "bin"))


def run_one(folder, layout, budget, log):
    cfg = json.load(open(os.path.join(folder, "config.json")))
    tag = f"{layout}_{budget}"
    cfg["vdb"] = {"enabled": True, "layout": layout, "level": "auto", "max_memory_mb": int(budget)}
    cfg["vdb_output"] = f"out/vdb_{tag}.vdb"
    path = os.path.join(folder, f"config_vdb_{tag}.json")
    with open(path, "w") as f:
        json.dump(cfg, f, indent=1)
    t = run_time_v([f"{BIN}/vispack-vdb", "--config", path, "--force"], log,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    report = json.load(open(os.path.join(folder, cfg.get("work_dir", "work"), "vdb", "report.json")))
    level = report["level"]
    estimate = {e["level"]: e for e in report["estimates"]}.get(level, {})
    out_dir = os.path.join(folder, os.path.dirname(cfg["vdb_output"]))
    for name in os.listdir(out_dir):
        if name.startswith(f"vdb_{tag}."):
            os.remove(os.path.join(out_dir, name))
    return {"dir": os.path.basename(os.path.abspath(folder)), "layout": layout, "budget": budget,
            "level": level, "layout_done": report.get("layout"),
            "parts": len(report.get("parts", [])) or 1,
            "active": report["quality"]["active_voxels"], "leaves": report["quality"]["leaves"],
            "mapped_mb": round(estimate.get("mapped_mb", 0.0), 1),
            "est_mb": round(estimate.get("estimated_mb", 0.0), 1),
            "peak_mib": round(t["peak_rss_mib"], 1), "cpu_s": round(t["cpu_s"], 2),
            "wall_s": t["wall_s"], "out_bytes": report.get("output_bytes")}


def main(argv):
    if len(argv) < 4 or argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if len(argv) > 1 and argv[1] in ("-h", "--help") else 2
    out_csv, rounds, specs = argv[1], int(argv[2]), argv[3:]
    rows = []
    for r in range(rounds):
        for spec in specs:
            folder, layout, budget = spec.rsplit(":", 2)
            log = os.path.join(folder, f"time_vdb_{layout}_{budget}_{r}.txt")
            rows.append(run_one(folder, layout, budget, log))
            print(rows[-1], flush=True)
    with open(out_csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))

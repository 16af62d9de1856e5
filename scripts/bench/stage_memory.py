#!/usr/bin/python3
"""Peak memory of each stage as the slice count grows: every stage executable run alone under
`/usr/bin/time -v` (`vispack-STAGE --config C --force --quiet --threads 2`) on phantoms that differ
only in their slice count, then the whole pipeline in one process (stage "run": `vispack-run C
--force --quiet --threads 2`, the streaming pass), so the peak a user sees is measured against the
slice count too. Writes one JSON object: {"rows": [{phantom, slices, width, height, stage,
seconds, peak_rss_mib, vdb_layout, vdb_level, vdb_parts}]} (the vdb_* keys on the vdb and run rows:
one file or parts, and how many). Prints one line per run to stderr.
Usage: stage_memory.py OUT_JSON PHANTOM_DIR...
VISPACK_BENCH_BIN: the folder of the executables (another build's, for a before/after)."""
import json
import os
import subprocess
import sys

from common import write_json
from stage_table import STAGES, peak_rss_mib
from time_v import read_time_v

BIN = os.environ["VISPACK_BENCH_BIN"]


def time_v_seconds(log):
    return read_time_v(log)["wall_s"]


def main():
    out, phantoms = sys.argv[1], sys.argv[2:]
    rows = []
    for ph in phantoms:
        ph = os.path.abspath(ph)
        truth = json.load(open(os.path.join(ph, "truth", "transforms.json")))
        config = os.path.join(ph, "config.json")
        for stage in STAGES + ["run"]:
            log = os.path.join(ph, f"memory-{stage}.time")
            if stage == "run":
                cmd = [f"{BIN}/vispack-run", config, "--force", "--quiet", "--threads", "2"]
            else:
                cmd = [f"{BIN}/vispack-{stage}", "--config", config, "--force", "--quiet", "--threads", "2"]
            subprocess.run(["/usr/bin/time", "-v", "-o", log] + cmd, check=True, stdout=subprocess.DEVNULL)
            rep = json.load(open(os.path.join(ph, "work", "vdb" if stage == "run" else stage, "report.json")))
            row = {"phantom": os.path.basename(ph), "slices": len(truth["slices"]),
                   "width": truth["width"], "height": truth["height"], "stage": stage,
                   "seconds": time_v_seconds(log) if stage == "run" else rep["seconds"],
                   "peak_rss_mib": peak_rss_mib(log)}
            if stage in ("vdb", "run"):
                row["vdb_layout"] = rep.get("layout", "file")
                row["vdb_level"] = rep.get("level")
                row["vdb_parts"] = len(rep.get("parts", [])) or 1
            rows.append(row)
            print(f"memory {os.path.basename(ph)} {stage}: {row['peak_rss_mib']:.0f} MiB"
                  + (f" (vdb level {row['vdb_level']}, {row['vdb_layout']}, {row['vdb_parts']} file(s))"
                     if "vdb_layout" in row else ""), file=sys.stderr)
    write_json(out, {"rows": rows})


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""Peak memory of each stage as the slice count grows: every stage executable run alone under
`/usr/bin/time -v` (`vispack-STAGE --config C --force --quiet --threads 2`) on phantoms that differ
only in their slice count. Prints one JSON object: {"rows": [{phantom, slices, width, height,
stage, seconds, peak_rss_mib}]}.
Usage: stage_memory.py OUT_JSON PHANTOM_DIR..."""
import json
import os
import subprocess
import sys

from common import write_json
from stage_table import STAGES, peak_rss_mib

BIN = os.environ["VISPACK_BENCH_BIN"]


def main():
    out, phantoms = sys.argv[1], sys.argv[2:]
    rows = []
    for ph in phantoms:
        ph = os.path.abspath(ph)
        truth = json.load(open(os.path.join(ph, "truth", "transforms.json")))
        for stage in STAGES:
            log = os.path.join(ph, f"memory-{stage}.time")
            subprocess.run(["/usr/bin/time", "-v", "-o", log, f"{BIN}/vispack-{stage}", "--config",
                            os.path.join(ph, "config.json"), "--force", "--quiet", "--threads", "2"],
                           check=True, stdout=subprocess.DEVNULL)
            rep = json.load(open(os.path.join(ph, "work", stage, "report.json")))
            rows.append({"phantom": os.path.basename(ph), "slices": len(truth["slices"]),
                         "width": truth["width"], "height": truth["height"], "stage": stage,
                         "seconds": rep["seconds"], "peak_rss_mib": peak_rss_mib(log)})
            print(f"memory {os.path.basename(ph)} {stage}: {rows[-1]['peak_rss_mib']:.0f} MiB", file=sys.stderr)
    write_json(out, {"rows": rows})


if __name__ == "__main__":
    main()

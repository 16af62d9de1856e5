#!/usr/bin/python3
"""One JSON line for the scaling table from a `/usr/bin/time -v vispack-run` log.
Usage: scaling_row.py NAME PHANTOM_DIR LOG"""
import json
import re
import sys

from time_v import parse_time_v

name, phantom, log = sys.argv[1:4]
text = open(log).read()
info = json.load(open(f"{phantom}/truth/transforms.json"))
tv = parse_time_v(text, log)
stages = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(\w+): ran \(.*?, ([\d.]+) s\)", text, re.M)}
slices = len(info["slices"])
print(json.dumps({"name": name, "preset": info.get("preset"), "width": info["width"],
                  "height": info["height"], "slices": slices,
                  "voxels": info["width"] * info["height"] * slices, "seconds": tv["wall_s"],
                  "cpu_seconds": tv["cpu_s"], "peak_rss_mib": tv["peak_rss_mib"], "stages": stages}))

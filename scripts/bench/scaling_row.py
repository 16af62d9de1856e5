#!/usr/bin/python3
"""One JSON line for the scaling table from a `/usr/bin/time -v vispack-run` log.
Usage: scaling_row.py NAME PHANTOM_DIR LOG"""
import json
import re
import sys

name, phantom, log = sys.argv[1:4]
text = open(log).read()
info = json.load(open(f"{phantom}/truth/transforms.json"))
wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", text).group(1)
seconds = 0.0
for part in wall.split(":"):
    seconds = seconds * 60 + float(part)
rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", text).group(1))
user = float(re.search(r"User time \(seconds\): ([\d.]+)", text).group(1))
system = float(re.search(r"System time \(seconds\): ([\d.]+)", text).group(1))
stages = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(\w+): ran \(.*?, ([\d.]+) s\)", text, re.M)}
slices = len(info["slices"])
print(json.dumps({"name": name, "preset": info.get("preset"), "width": info["width"],
                  "height": info["height"], "slices": slices,
                  "voxels": info["width"] * info["height"] * slices, "seconds": seconds,
                  "cpu_seconds": user + system, "peak_rss_mib": rss_kb / 1024, "stages": stages}))

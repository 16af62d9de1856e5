#!/usr/bin/python3
"""The one reader of `/usr/bin/time -v` logs for the benchmark scripts (standard library only).

    parse_time_v(text) -> dict(wall_s, user_s, system_s, cpu_s, peak_rss_kib, peak_rss_mib)
    run_time_v(cmd, log, **kw) -> the same, after running cmd (a list) under /usr/bin/time -v
                                  with its log in `log` (subprocess.run keywords pass through)

From a shell: `time_v.py LOG [FIELD...]` prints the fields (default: all) comma-separated, in
the order given; e.g. `time_v.py t.txt peak_rss_kib user_s system_s wall_s`.
"""
import re
import subprocess
import sys

FIELDS = ("wall_s", "user_s", "system_s", "cpu_s", "peak_rss_kib", "peak_rss_mib")


def parse_time_v(text, source="time -v log"):
    def field(name):
        m = re.search(re.escape(name) + r": ([0-9.:]+)", text)
        if not m:
            raise ValueError(f"{source}: no '{name}' line (not a /usr/bin/time -v log?)")
        return m.group(1)

    wall_s = 0.0
    for part in field("Elapsed (wall clock) time (h:mm:ss or m:ss)").split(":"):
        wall_s = wall_s * 60 + float(part)
    user_s = float(field("User time (seconds)"))
    system_s = float(field("System time (seconds)"))
    rss_kib = int(field("Maximum resident set size (kbytes)"))
    return {"wall_s": round(wall_s, 2), "user_s": user_s, "system_s": system_s,
            "cpu_s": user_s + system_s, "peak_rss_kib": rss_kib, "peak_rss_mib": rss_kib / 1024}


def read_time_v(log):
    with open(log) as f:
        return parse_time_v(f.read(), log)


def run_time_v(cmd, log, **kw):
    subprocess.run(["/usr/bin/time", "-v", "-o", log] + list(cmd), check=True, **kw)
    return read_time_v(log)


def main(argv):
    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if len(argv) >= 2 else 2
    fields = argv[2:] or list(FIELDS)
    bad = [f for f in fields if f not in FIELDS]
    if bad:
        print(f"time_v.py: unknown field {bad[0]} (fields: {', '.join(FIELDS)})", file=sys.stderr)
        return 2
    try:
        values = read_time_v(argv[1])
    except (OSError, ValueError) as e:
        print(f"time_v.py: {e}", file=sys.stderr)
        return 1
    print(",".join(str(values[f]) for f in fields))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))

#!/usr/bin/python3
"""The sections of docs/BENCHMARKS.md measured by hand, which a full scripts/bench.sh run carries
over unchanged. Each is marked by a line `<!-- kept after: NAME; measured: COMMIT YYYY-MM-DD -->`
(NAME: the generated section it follows, e.g. registration; COMMIT (7 to 40 hex digits) and the
date: when its numbers were measured), so a reader can tell how old a number is.
Usage: kept_sections.py DOCS_DIR   checks every marker of DOCS_DIR/BENCHMARKS.md (exit 1 naming
the first bad one), so a bad marker fails the test run, not the report at the end of an hour-long
benchmark run. Standard library only."""
import os
import re
import sys

MARKER = re.compile(r"<!-- kept after: (\w+)(.*?)-->")
MEASURED = re.compile(r"; measured: [0-9a-f]{7,40} \d{4}-\d\d-\d\d $")


def read_kept_sections(path):
    """{NAME: [section text, ...]} of the kept sections of the report at `path` (empty when it
    does not exist). Raises ValueError naming the section whose marker lacks its commit and date."""
    kept = {}
    if not os.path.exists(path):
        return kept
    sections, current = [], None
    for line in open(path, encoding="utf-8").read().splitlines():
        if line.startswith("## "):
            current = [line]
            sections.append(current)
        elif current is not None:
            current.append(line)
    for lines in sections:
        for line in lines:
            m = MARKER.match(line.strip())
            if m:
                if not MEASURED.match(m.group(2)):
                    raise ValueError(f"the kept section '{lines[0]}' has no "
                                     "'measured: COMMIT YYYY-MM-DD' in its marker")
                kept.setdefault(m.group(1), []).append("\n".join(lines).rstrip() + "\n")
                break
    return kept


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    path = os.path.join(sys.argv[1], "BENCHMARKS.md")
    if not os.path.exists(path):
        raise SystemExit(f"kept_sections.py: {path} does not exist")
    try:
        kept = read_kept_sections(path)
    except ValueError as e:
        raise SystemExit(f"kept_sections.py: {path}: {e}")
    print(f"kept_sections.py: {path}: {sum(len(v) for v in kept.values())} kept sections, "
          "every marker with its commit and date")

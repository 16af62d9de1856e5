#!/usr/bin/python3
"""Runs every example in README.md as written (the README's promise: copy, paste, it works).

Every fenced code block in the README carries a marker, an HTML comment on the line(s) just above
it (invisible on a rendered page), saying what the block is:

  <!-- example file: NAME -->     the block is a file's content (a config): written to NAME
                                  (a ```json block must be strict JSON)
  <!-- example run -->            a shell block: run with bash -euo pipefail, line by line as one
                                  script
  <!-- example python -->         a Python block: run with /usr/bin/python3, PYTHONPATH=python
  <!-- example skip: REASON -->   not run, for the reason given (a diagram, the test suite itself,
                                  a cluster)
  <!-- example setup: COMMAND --> run before the block (with any of the above), hidden from the
                                  reader: makes the data an example needs (a small phantom where an
                                  example needs the demo's output)

A block without a marker, a marker without a block, or a skip without a reason fails the test.
The blocks run in README order in one scratch folder that holds links to the build (build/), the
source's scripts/, python/ and configs/, so paths read exactly as in the README (build/bin/...).

Usage: readme_examples.py SOURCE_DIR BUILD_DIR [--keep]
"""

import json
import os
import re
import subprocess
import sys
import tempfile

MARKER = re.compile(r"^<!-- example (file|run|python|skip|setup)(?::\s*(.*?))?\s*-->$")
FENCE = re.compile(r"^```(\w*)\s*$")


class ReadmeError(Exception):
    pass


def parse(path):
    """[(line, kind, argument, language, text, setups)] for every fenced block, in order."""
    lines = open(path, encoding="utf-8").read().split("\n")
    blocks, markers, i = [], [], 0
    while i < len(lines):
        line = lines[i]
        m = MARKER.match(line.strip())
        if m:
            markers.append((i + 1, m.group(1), (m.group(2) or "").strip()))
            i += 1
            continue
        f = FENCE.match(line)
        if f:
            start = i + 1
            body = []
            i += 1
            while i < len(lines) and not lines[i].startswith("```"):
                body.append(lines[i])
                i += 1
            if i == len(lines):
                raise ReadmeError(f"README.md:{start}: code block never closed")
            setups = [arg for (_, kind, arg) in markers if kind == "setup"]
            kinds = [(n, kind, arg) for (n, kind, arg) in markers if kind != "setup"]
            if len(kinds) != 1:
                raise ReadmeError(
                    f"README.md:{start}: a code block needs exactly one example marker "
                    "(file, run, python or skip) on the lines above it, found "
                    f"{[k for (_, k, _) in kinds] or 'none'}")
            _, kind, arg = kinds[0]
            if kind in ("skip", "file") and not arg:
                raise ReadmeError(f"README.md:{start}: 'example {kind}' needs an argument")
            if any(not s for s in setups):
                raise ReadmeError(f"README.md:{start}: 'example setup' needs a command")
            blocks.append((start, kind, arg, f.group(1), "\n".join(body) + "\n", setups))
            markers = []
            i += 1
            continue
        if markers and line.strip():
            raise ReadmeError(
                f"README.md:{markers[0][0]}: an example marker not followed by a code block")
        i += 1
    if markers:
        raise ReadmeError(f"README.md:{markers[0][0]}: an example marker at the end of the file")
    return blocks


def run(command, cwd, env, what):
    done = subprocess.run(command, cwd=cwd, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)
    sys.stdout.write(done.stdout)
    if done.returncode != 0:
        raise ReadmeError(f"{what}: exit {done.returncode}")


def main():
    if len(sys.argv) < 3:
        print(__doc__)
        return 2
    source, build = os.path.abspath(sys.argv[1]), os.path.abspath(sys.argv[2])
    keep = "--keep" in sys.argv[3:]
    blocks = parse(os.path.join(source, "README.md"))
    scratch = tempfile.mkdtemp(prefix="vispack-readme-")
    for name, target in (("build", build), ("scripts", os.path.join(source, "scripts")),
                         ("python", os.path.join(source, "python")),
                         ("configs", os.path.join(source, "configs"))):
        os.symlink(target, os.path.join(scratch, name))
    env = dict(os.environ, PYTHONPATH=os.path.join(scratch, "python"),
               PYTHONDONTWRITEBYTECODE="1")
    counts = {}
    try:
        for (start, kind, arg, language, text, setups) in blocks:
            counts[kind] = counts.get(kind, 0) + 1
            for command in setups:
                print(f"== README.md:{start}: setup: {command}")
                run(["bash", "-euo", "pipefail", "-c", command], scratch, env,
                    f"README.md:{start}: setup '{command}'")
            if kind == "skip":
                print(f"== README.md:{start}: skipped ({arg})")
            elif kind == "file":
                if language == "json":
                    try:
                        json.loads(text)
                    except ValueError as e:
                        raise ReadmeError(f"README.md:{start}: {arg} is not strict JSON: {e}")
                with open(os.path.join(scratch, arg), "w", encoding="utf-8") as out:
                    out.write(text)
                print(f"== README.md:{start}: wrote {arg}")
            elif kind == "run":
                print(f"== README.md:{start}: run\n{text}", end="")
                run(["bash", "-euo", "pipefail", "-c", text], scratch, env,
                    f"README.md:{start}: shell example")
            elif kind == "python":
                print(f"== README.md:{start}: python\n{text}", end="")
                run(["/usr/bin/python3", "-c", text], scratch, env,
                    f"README.md:{start}: Python example")
    except ReadmeError as e:
        print(f"FAIL {e} (scratch folder {scratch} kept)")
        return 1
    if not keep:
        subprocess.run(["rm", "-rf", scratch])
    print(f"README examples: {counts.get('run', 0)} shell, {counts.get('python', 0)} Python, "
          f"{counts.get('file', 0)} files written, {counts.get('skip', 0)} skipped with reasons")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except ReadmeError as e:
        print(f"FAIL {e}")
        sys.exit(1)

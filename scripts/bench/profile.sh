#!/usr/bin/env bash
# Where each pipeline stage spends its time: a sampling profile (perf record -e cpu-clock; the
# hardware counters are not available in this container) of every stage on a phantom whose
# pipeline has run, or valgrind --tool=callgrind when perf cannot record. Writes OUT/<stage>.txt
# (top functions by self time) and OUT/tool.txt (which profiler).
# Usage: scripts/bench/profile.sh PHANTOM_DIR OUT_DIR   (needs VISPACK_BENCH_BIN)
set -euo pipefail
phantom=$1 out=$2
bin=${VISPACK_BENCH_BIN:?}
mkdir -p "$out"
stages=(register mask labels pack vdb)
if perf record -e cpu-clock -o "$out/probe.data" -- true >/dev/null 2>&1; then
  echo "perf record -e cpu-clock (sampling, $(perf --version))" >"$out/tool.txt"
  for s in "${stages[@]}"; do
    perf record -e cpu-clock -F 499 -o "$out/$s.data" -- \
      "$bin/vispack-$s" --config "$phantom/config.json" --force --quiet >"$out/$s.log" 2>&1 ||
      { cat "$out/$s.log"; echo "profile.sh: vispack-$s failed" >&2; exit 1; }
    # The report to a file, then its first 12 rows (a `| head` would end perf report or grep
    # with SIGPIPE when there are more, and pipefail would take that for a failure).
    perf report -i "$out/$s.data" --stdio --no-children --sort dso,symbol --percent-limit 1.5 \
      >"$out/$s.report" 2>/dev/null
    awk '/^ +[0-9.]+%/ && n++ < 12' "$out/$s.report" >"$out/$s.txt"
    rm -f "$out/$s.data" "$out/$s.report"
  done
  rm -f "$out/probe.data"
else
  echo "valgrind --tool=callgrind" >"$out/tool.txt"
  for s in "${stages[@]}"; do
    valgrind --tool=callgrind --callgrind-out-file="$out/$s.cg" \
      "$bin/vispack-$s" --config "$phantom/config.json" --force --quiet --threads 1 >"$out/$s.log" 2>&1 ||
      { cat "$out/$s.log"; echo "profile.sh: vispack-$s failed under callgrind" >&2; exit 1; }
    callgrind_annotate "$out/$s.cg" >"$out/$s.report" 2>/dev/null
    awk '/^ *[0-9,]+ \(/ && n++ < 12' "$out/$s.report" >"$out/$s.txt"
    rm -f "$out/$s.cg" "$out/$s.report"
  done
fi

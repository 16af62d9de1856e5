#!/usr/bin/env bash
# The streaming vispack-run against --staged, interleaved (A B A B), ROUNDS rounds at --threads 1
# and 2: one line per run "MODE THREADS ROUND USER_S SYS_S WALL_S MAXRSS_KB load=L" on stdout
# (docs/BENCHMARKS.md "Streaming run"). Takes medians of user + sys yourself.
# Usage: scripts/bench/stream_ab.sh BIN_DIR PHANTOM_DIR [ROUNDS]   (PHANTOM_DIR from
#   vispack-phantom --preset vhp --slices 16 --seed 1 --out PHANTOM_DIR)
set -euo pipefail
bin=$1 phantom=$2 rounds=${3:-3}
times=$(mktemp)
trap 'rm -f "$times"' EXIT
for round in $(seq 1 "$rounds"); do
  for threads in 1 2; do
    for mode in stream staged; do
      flag=()
      [ "$mode" = staged ] && flag=(--staged)
      /usr/bin/time -f "%U %S %e %M" -o "$times" "$bin/vispack-run" "$phantom/config.json" \
        --force --quiet --threads "$threads" "${flag[@]}" >/dev/null
      echo "$mode $threads $round $(cat "$times") load=$(cut -d' ' -f1 /proc/loadavg)"
    done
  done
done

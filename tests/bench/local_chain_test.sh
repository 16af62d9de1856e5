#!/usr/bin/env bash
# scripts/bench/local_chain.py (the cluster chain run locally, for machines without SLURM):
# 2 shards of the tiny phantom give the packed file vispack-run gives, byte for byte; a stage
# that fails stops the chain with exit 1, naming the step, the task and the command.
# Usage: local_chain_test.sh BIN_DIR
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
bin=$(cd "${1:?usage: local_chain_test.sh BIN_DIR}" && pwd)
tmp=$(mktemp -d "${TMPDIR:-/tmp}/vispack-local-chain-test-XXXXXX")
trap 'rm -rf "$tmp"' EXIT
"$bin/vispack-phantom" --out "$tmp/ph" --preset tiny --seed 3 --quiet >/dev/null
cp -a "$tmp/ph" "$tmp/local"
cp -a "$tmp/ph" "$tmp/chain"
"$bin/vispack-run" "$tmp/local/config.json" --threads 1 --quiet >/dev/null
/usr/bin/python3 "$root/scripts/bench/local_chain.py" "$tmp/chain/config.json" --bin "$bin" \
  --shards 2 --json "$tmp/chain.json" >"$tmp/chain.out"
cat "$tmp/chain.out"
grep -q '^register-measure: 2 task(s)' "$tmp/chain.out"
grep -q '^chain: 2 worker(s), [0-9.]* s$' "$tmp/chain.out"
cmp "$tmp/local/out/volume.vpk" "$tmp/chain/out/volume.vpk"
/usr/bin/python3 -c 'import json, sys; d = json.load(open(sys.argv[1])); assert d["shards"] == 2 and d["steps"][0]["tasks"] == 2, d' "$tmp/chain.json"
# A stage that fails: the chain stops with exit 1 and names it.
mkdir "$tmp/broken"
for tool in "$bin"/vispack-*; do ln -s "$tool" "$tmp/broken/"; done
rm "$tmp/broken/vispack-register"
printf '#!/bin/sh\necho "disk on fire" >&2\nexit 3\n' >"$tmp/broken/vispack-register"
chmod +x "$tmp/broken/vispack-register"
cp -a "$tmp/ph" "$tmp/fail"
rc=0
/usr/bin/python3 "$root/scripts/bench/local_chain.py" "$tmp/fail/config.json" --bin "$tmp/broken" \
  --shards 2 >"$tmp/fail.out" 2>&1 || rc=$?
cat "$tmp/fail.out"
[[ $rc == 1 ]] || { echo "expected exit 1, got $rc"; exit 1; }
grep -q 'step register-measure, task [01]: exit 3: .*vispack-register' "$tmp/fail.out"
grep -q 'disk on fire' "$tmp/fail.out"
echo "local_chain: byte-identical to vispack-run; a failed step named"

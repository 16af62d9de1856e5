#!/usr/bin/env bash
# scripts/vispack-slurm --dry-run without a cluster: the job chain it would submit (one array per
# sharded stage, afterok dependencies, --kill-on-invalid-dep, shard bounds from the array task),
# run here as SLURM would run it (each array task with its SLURM_ARRAY_TASK_ID, in chain order),
# gives the local run's packed file byte for byte; and its usage errors.
# Usage: tests/cluster/dry_run_test.sh BIN_DIR
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
bin=$(cd "${1:?usage: dry_run_test.sh BIN_DIR}" && pwd)
tmp=$(mktemp -d "${TMPDIR:-/tmp}/vispack-slurm-dry-XXXXXX")
trap 'rm -rf "$tmp"' EXIT
fail() { echo "FAIL: $*"; exit 1; }

"$bin/vispack-phantom" --out "$tmp/ph" --preset tiny --seed 2 --quiet >/dev/null
sed -i 's/"brick_edge": *[0-9]*/"brick_edge": 8/' "$tmp/ph/config.json"
cp -a "$tmp/ph" "$tmp/local"
cp -a "$tmp/ph" "$tmp/my dir"  # a path with a space
config="$tmp/my dir/config.json"
"$root/scripts/vispack-slurm" "$config" --shards 3 --bin "$bin" --jobs-dir "$tmp/jobs" \
  --partition short --dry-run >"$tmp/dry.out"
[[ ! -e $tmp/jobs ]] || fail "--dry-run wrote the jobs folder"
mapfile -t scripts < <(sed -n 's/^### \([^ ]*\.sh\)$/\1/p' "$tmp/dry.out")
names=$(for s in "${scripts[@]}"; do basename "$s"; done | tr '\n' ' ')
expected="01-register-measure.sh 02-register-solve.sh 03-slices.sh 04-pack.sh 05-pack-merge.sh 06-vdb.sh "
[[ $names == "$expected" ]] || fail "jobs: '$names', expected '$expected'"
[[ $(grep -c '^### sbatch --parsable --kill-on-invalid-dep=yes --dependency=afterok:<' "$tmp/dry.out") == 5 ]] ||
  fail "every job but the first must depend on the previous one with afterok"
[[ $(grep -c '^#SBATCH --array=0-2$' "$tmp/dry.out") == 4 ]] || fail "4 sharded jobs (measure, per-slice stages, pack, vdb) with --array=0-2"
[[ $(grep -c '^#SBATCH --partition=short$' "$tmp/dry.out") == 6 ]] || fail "--partition in every job"
grep -q 'sacct' "$tmp/dry.out" && fail "the job scripts must not use sacct"

# Run the printed scripts as SLURM would: split them out, each array task with its ID, in order.
mkdir -p "$tmp/run"
awk -v dir="$tmp/run" '/^### sbatch/ { f = ""; next }
                       /^### \// { n++; f = sprintf("%s/%02d.sh", dir, n); next }
                       f { print > f }' "$tmp/dry.out"
[[ $(ls "$tmp/run" | wc -l) == 6 ]] || fail "could not split the 6 job scripts out of the dry run"
for script in "$tmp"/run/*.sh; do
  if grep -q '^#SBATCH --array=0-2$' "$script"; then
    for i in 0 1 2; do SLURM_ARRAY_TASK_ID=$i bash "$script" || fail "$script task $i"; done
  else
    bash "$script" || fail "$script"
  fi
done
# A task outside the array is refused.
if SLURM_ARRAY_TASK_ID=3 bash "$tmp/run/04.sh" 2>/dev/null; then fail "task 3 of 0..2 accepted"; fi
"$bin/vispack-run" "$tmp/local/config.json" --quiet >/dev/null
cmp "$tmp/local/out/volume.vpk" "$tmp/my dir/out/volume.vpk" ||
  fail "the job chain's packed file differs from the local run"
ls "$tmp/my dir/work/pack-slabs/"slab_000{0,1,2}.vpkslab >/dev/null || fail "no slab files: pack did not shard"
# The OpenVDB export in three parts, one per shard, and no whole file.
parts=$(cd "$tmp/my dir/out" && ls -- *.slices-*.vdb 2>/dev/null | tr '\n' ' ')
[[ $parts == "volume.slices-0000-0008.vdb volume.slices-0008-0016.vdb volume.slices-0016-0024.vdb " ]] ||
  fail "OpenVDB parts: '$parts'"
[[ ! -e "$tmp/my dir/out/volume.vdb" ]] || fail "a sharded vdb step wrote the whole file too"

# Usage errors: one line, exit 2 (3 for a missing config).
set +e
"$root/scripts/vispack-slurm" "$config" --shards x --dry-run 2>"$tmp/err"
[[ $? == 2 && $(cat "$tmp/err") == "vispack-slurm: error: --shards 'x' is not a positive integer" ]] ||
  fail "--shards x: $(cat "$tmp/err")"
"$root/scripts/vispack-slurm" "$tmp/none.json" --dry-run 2>"$tmp/err"
[[ $? == 3 ]] || fail "missing config: $(cat "$tmp/err")"
"$root/scripts/vispack-slurm" --help | grep -q '^Usage: vispack-slurm CONFIG' || fail "--help"
echo "PASS: vispack-slurm --dry-run chain run by hand gives the local packed file"

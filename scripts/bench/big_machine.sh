#!/usr/bin/env bash
# The figures only a many-core machine (and a real GPU) can give, in one run of at most
# VISPACK_BIG_DEADLINE_S seconds (docs/BENCHMARKS.md "On a GPU machine with 16 cores"). Runs from a
# bundle (scripts/bench/bundle.sh: the executables and their libraries, for a machine without the
# project's packages) or a build's bin folder. Phases, most wanted first; each is skipped with a
# message when the time left is under its estimate, and a failed phase does not stop the others:
#   1. machine_bench --workers 2,4,8: what K worker processes get at best (compute, fresh memory,
#      memory reads): the ceiling the chain's speed-up is read against
#   2. the viewer on a synthetic X×Y×Z stack (VISPACK_BIG_VIEWER_STACK, default 2048,1216,128,
#      bricks of 64, written by viewer_bench --stack): every mode at level 0 (--level 0) at a
#      FRAME² frame (default 1024), then every mode at the level the footprint asks for
#   3. the cluster chain (scripts/cluster_plan.py, run by scripts/bench/local_chain.py: each
#      step's shards at once as processes, no SLURM) on the vhp phantom (VISPACK_BIG_PRESET: its
#      2048×1216×SLICES,
#      pack.brick_edge EDGE so that the stack has 8 whole slabs: default 256 and 32) with
#      1, 8, 4, 2 workers (VISPACK_BIG_WORKERS), each chain's packed file compared byte for byte
#      with the one-worker chain's; the page cache is emptied before each chain
#   4. the pack encoder against `zstd -3 -T2` on the same level-0 bytes (those of the one-worker
#      chain's file), alternated, VISPACK_BIG_ROUNDS rounds (default 2): format_writer_raw_bench
#      (bricks of 64, the pack's default, whatever the chain's EDGE) against zstd, wall and CPU
#      seconds of each; then both on every core once
#   5. the viewer on the chain's packed file (the largest here), every mode at level 0
# Exit 0 when no phase failed (a skipped one is not a failure; the log says which), 1 otherwise.
# Usage: scripts/bench/big_machine.sh BUNDLE_OR_BIN_DIR OUT_DIR [WORK_DIR]
#   BUNDLE: a folder with bin/ and lib/ (bundle.sh); or a build's bin folder
#   OUT_DIR: big_machine.log (everything printed), viewer-stack.json, viewer-chain.json,
#            chains.json; WORK_DIR (default a temporary folder, removed at the end) holds the data
set -uo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
src=$(cd "${1:?usage: big_machine.sh BUNDLE_OR_BIN_DIR OUT_DIR [WORK_DIR]}" && pwd) || exit 2
out=${2:?usage: big_machine.sh BUNDLE_OR_BIN_DIR OUT_DIR [WORK_DIR]}
mkdir -p "$out" || exit 2
out=$(cd "$out" && pwd)
if [[ -d $src/bin && -d $src/lib ]]; then
  bin=$src/bin
  export LD_LIBRARY_PATH=$src/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
else
  bin=$src
fi
for program in vispack-run vispack-phantom viewer_bench machine_bench; do
  [[ -x $bin/$program ]] || { echo "big_machine.sh: $bin/$program: not found" >&2; exit 2; }
done
# local_chain.py beside this script, cluster_plan.py one folder up (as in the repository).
[[ -f $here/local_chain.py && -f $here/../cluster_plan.py ]] ||
  { echo "big_machine.sh: $here: local_chain.py or ../cluster_plan.py missing" >&2; exit 2; }
if [[ -n ${3:-} ]]; then
  work=$3
  mkdir -p "$work" || exit 2
else
  work=$(mktemp -d "${TMPDIR:-/tmp}/vispack-big-XXXXXX") || exit 2
  trap 'rm -rf "$work"' EXIT
fi
exec > >(tee "$out/big_machine.log") 2>&1
deadline_s=${VISPACK_BIG_DEADLINE_S:-540}
preset=${VISPACK_BIG_PRESET:-vhp}
slices=${VISPACK_BIG_SLICES:-256}
edge=${VISPACK_BIG_EDGE:-32}
workers=${VISPACK_BIG_WORKERS:-1 8 4 2}
stack=${VISPACK_BIG_VIEWER_STACK:-2048,1216,128}
frame=${VISPACK_BIG_FRAME:-1024}
reps=${VISPACK_BIG_REPS:-5}
rounds=${VISPACK_BIG_ROUNDS:-2}
gpu_mb=${VISPACK_BIG_GPU_MB:-16384}
modes=colour,ct,labels,tf2d,iso,mip,average,mpr  # every mode of vispack-view
zstd_bin=$bin/zstd
[[ -x $zstd_bin ]] || zstd_bin=$(command -v zstd || echo zstd)
failed=()
start=$(date +%s)
left() { echo $((deadline_s - ($(date +%s) - start))); }
# phase NAME ESTIMATE_S FUNCTION: runs it when ESTIMATE_S seconds are left, says how it ended.
phase() {
  local name=$1 estimate=$2
  shift 2
  echo
  echo "== [$(($(date +%s) - start)) s] $name (estimate ${estimate} s, $(left) s left)"
  if (($(left) < estimate)); then
    echo "== $name: skipped, $(left) s left against an estimate of $estimate s"
    return 0
  fi
  local t0 rc=0
  t0=$(date +%s.%N)
  "$@" || rc=$?
  ((rc == 0)) || failed+=("$name")
  echo "== $name: $( ((rc == 0)) && echo done || echo "FAILED (exit $rc)") in $(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }') s"
}
# timed LABEL CMD...: runs CMD, prints LABEL with its wall and CPU seconds (user+sys, children).
timed() {
  local label=$1
  shift
  python3 - "$label" "$@" <<'PY'
import resource, subprocess, sys, time
label, cmd = sys.argv[1], sys.argv[2:]
t0 = time.monotonic()
code = subprocess.call(cmd, stdout=subprocess.DEVNULL)
wall = time.monotonic() - t0
r = resource.getrusage(resource.RUSAGE_CHILDREN)
print(f"{label}: wall {wall:.2f} s, CPU {r.ru_utime + r.ru_stime:.2f} s "
      f"(user {r.ru_utime:.2f}, sys {r.ru_stime:.2f}), peak RSS {r.ru_maxrss / 1024:.0f} MiB"
      + ("" if code == 0 else f", EXIT {code}"), flush=True)
sys.exit(code)
PY
}
drop_caches() { sync; echo 3 >/proc/sys/vm/drop_caches 2>/dev/null || true; }

machine_info() {
  echo "machine: $(nproc) cores, $(awk '/MemTotal/ { printf "%.1f GiB", $2 / 1048576 }' /proc/meminfo), load $(cut -d' ' -f1-3 /proc/loadavg)"
  echo "cpu: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2-)"
  echo "os: $(. /etc/os-release 2>/dev/null && echo "$PRETTY_NAME"); glibc $(getconf GNU_LIBC_VERSION 2>/dev/null)"
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  echo "disk: $(df -h "$work" | tail -1)"
  echo "settings: preset $preset, slices $slices, edge $edge, workers $workers, viewer stack $stack, frame $frame, reps $reps, rounds $rounds, deadline $deadline_s s"
}

machine_ceiling() {
  # shellcheck disable=SC2086  # VISPACK_BIG_MACHINE_BENCH: options, split on purpose
  "$bin/machine_bench" --workers 2,4,8 \
    ${VISPACK_BIG_MACHINE_BENCH:---rounds 2 --compute-steps 500000000 --settle-s 1}
}

# viewer_on FILE JSON [footprint]: every mode at level 0 (with its PSNR against the CPU reference
# when VISPACK_BIG_PSNR=1: a whole-level reference per row, minutes at 1024²), then, with
# "footprint", every mode at the level the screen footprint asks for.
viewer_on() {
  local file=$1 json=$2 psnr=()
  [[ ${VISPACK_BIG_PSNR:-0} == 1 ]] && psnr=(--psnr)
  "$bin/viewer_bench" --file "$file" --size "$frame" --paged-only --level 0 "${psnr[@]}" \
    --modes "$modes" --max-gpu-mb "$gpu_mb" --reps "$reps" --json "$json" || return
  [[ ${3:-} == footprint ]] || return 0
  "$bin/viewer_bench" --file "$file" --size "$frame" --paged-only --max-gpu-mb 2048 \
    --modes "$modes" --reps "$reps" --json "${json%.json}-footprint.json"
}

viewer_stack() {
  "$bin/viewer_bench" --stack "$stack" --keep "$work/stack.vpk" || return
  viewer_on "$work/stack.vpk" "$out/viewer-stack.json" footprint
}

chain_phantom() {
  rm -rf "$work/vhp"
  timed "vispack-phantom $preset $slices slices, $(nproc) threads" "$bin/vispack-phantom" \
    --out "$work/vhp" --preset "$preset" --slices "$slices" --seed 1 --threads "$(nproc)" --quiet ||
    return
  sed -i "s/\"brick_edge\": *[0-9]*/\"brick_edge\": $edge/" "$work/vhp/config.json"
  grep -q "\"brick_edge\": $edge" "$work/vhp/config.json" ||
    { echo "no brick_edge in $work/vhp/config.json"; return 1; }
  du -sh "$work/vhp"
}

chain_once() {
  local w=$1
  rm -rf "$work/vhp/work" "$work/vhp/out"
  drop_caches
  python3 "$here/local_chain.py" "$work/vhp/config.json" --bin "$bin" --shards "$w" \
    --json "$work/chain-$w.json" || return
  if [[ $w == 1 ]]; then
    cp "$work/vhp/out/volume.vpk" "$work/chain.vpk"
  elif [[ -f $work/chain.vpk ]]; then
    cmp -s "$work/chain.vpk" "$work/vhp/out/volume.vpk" &&
      echo "chain $w: packed file byte-identical to the one-worker chain's" ||
      { echo "chain $w: packed file DIFFERS from the one-worker chain's"; return 1; }
  fi
}

# chain_runs W...: one chain per worker count; a count is skipped when the time left is under
# its estimate from the one-worker chain (one_s, set by the run of 1).
one_s=0
chain_runs() {
  local w
  for w in "$@"; do
    if ((one_s > 0)); then
      # A chain of w workers takes about 1/w of the one-worker chain, plus its fixed part.
      local estimate=$((one_s / w + one_s / 8 + 10))
      if (($(left) < estimate)); then
        echo "chain $w: skipped, $(left) s left against an estimate of $estimate s"
        continue
      fi
    fi
    local t0
    t0=$(date +%s)
    chain_once "$w" || return
    [[ $w == 1 ]] && one_s=$(($(date +%s) - t0))
  done
  return 0
}

chains_summary() {
  compgen -G "$work/chain-*.json" >/dev/null || { echo "no chain ran"; return 0; }
  python3 - "$out/chains.json" "$work"/chain-*.json <<'PY'
import json, sys
chains = [json.load(open(p)) for p in sys.argv[2:]]
chains.sort(key=lambda c: c["shards"])
json.dump(chains, open(sys.argv[1], "w"), indent=1)
one = next((c["wall_s"] for c in chains if c["shards"] == 1), None)
for c in chains:
    steps = ", ".join(f"{s['name']} {s['wall_s']:.1f}" for s in c["steps"])
    speed = f", speed-up {one / c['wall_s']:.2f}x" if one else ""
    print(f"chain {c['shards']} worker(s): {c['wall_s']:.1f} s{speed} ({steps})")
PY
}

encoder_vs_zstd() {
  [[ -f $work/chain.vpk ]] || { echo "no one-worker chain file to take the bytes from"; return 1; }
  local ch r
  for ch in rgba ct labels; do
    "$bin/vispack-extract" "$work/chain.vpk" --channel "$ch" -o "$work/$ch.nrrd" >/dev/null || return
  done
  cat "$work/rgba.nrrd" "$work/ct.nrrd" "$work/labels.nrrd" >"$work/raw"
  echo "level-0 bytes: $(stat -c %s "$work/raw") (rgba, ct, labels NRRDs)"
  for r in $(seq "$rounds"); do
    rm -f "$work/enc.vpk"
    "$bin/format_writer_raw_bench" "$work/chain.vpk" "$work/enc.vpk" "$work/rgba.nrrd" \
      "$work/ct.nrrd" "$work/labels.nrrd" --zstd-level 3 --threads 2 --brick-edge 64 | sed "s/^/round $r encoder -3 T2: /" || return
    echo "round $r encoder bytes: $(stat -c %s "$work/enc.vpk")"
    timed "round $r zstd -3 -T2" "$zstd_bin" -3 -T2 -q -f "$work/raw" -o "$work/raw.zst" || return
    echo "round $r zstd bytes: $(stat -c %s "$work/raw.zst")"
  done
  # Once more on every core.
  local cores
  cores=$(nproc)
  rm -f "$work/enc.vpk"
  "$bin/format_writer_raw_bench" "$work/chain.vpk" "$work/enc.vpk" "$work/rgba.nrrd" \
    "$work/ct.nrrd" "$work/labels.nrrd" --zstd-level 3 --threads "$cores" --brick-edge 64 |
    sed "s/^/encoder -3 T$cores: /" || return
  timed "zstd -3 -T$cores" "$zstd_bin" -3 -T"$cores" -q -f "$work/raw" -o "$work/raw.zst" || return
  rm -f "$work"/*.nrrd "$work/raw" "$work/raw.zst" "$work/enc.vpk"
}

viewer_chain() {
  [[ -f $work/chain.vpk ]] || { echo "no chain file"; return 1; }
  viewer_on "$work/chain.vpk" "$out/viewer-chain.json"
}

phase "machine" 0 machine_info
phase "machine_bench: K workers at best" 60 machine_ceiling
phase "viewer, synthetic $stack, ${frame}² frames" 150 viewer_stack
phase "$preset phantom, $slices slices" 90 chain_phantom
# The one-worker chain first: its packed file is the others' reference and the encoder's input.
first_workers=() other_workers=()
for w in $workers; do
  if [[ $w == 1 ]]; then first_workers+=(1); else other_workers+=("$w"); fi
done
phase "cluster chain, one worker" 120 chain_runs "${first_workers[@]}"
phase "cluster chain, workers ${other_workers[*]}" 30 chain_runs "${other_workers[@]}"
phase "cluster chain summary" 0 chains_summary
phase "pack encoder against zstd -3 -T2" 80 encoder_vs_zstd
phase "viewer, the chain's file" 60 viewer_chain
echo
echo "== big_machine.sh: $(($(date +%s) - start)) s in all"
if ((${#failed[@]})); then
  echo "== FAILED: ${failed[*]}"
  exit 1
fi

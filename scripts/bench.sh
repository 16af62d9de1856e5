#!/usr/bin/env bash
# Regenerates the benchmark report: builds Release, generates the phantom inputs, runs every
# benchmark with its peers in the same run, and writes docs/BENCHMARKS.md and docs/img/*.png.
# Usage: scripts/bench.sh [--quick] [--no-report] [--build DIR] [--no-build] [--require-clean]
#   --quick      a reduced set (tiny phantom, one repetition, no profile) in under 3 minutes
#   --no-report  measure only; docs/ is not touched (scripts/test.sh runs --quick --no-report)
#   --build DIR  build folder (default build/, or $VISPACK_BENCH_BUILD)
#   --no-build   use the executables already in DIR/bin (skip scripts/build.sh)
#   --full-length  instead of the report: scripts/bench/full_length.sh --report (the whole male at
#                full length: about 45 minutes and 25 GB of disk; its own options after it)
#   --require-clean  refuse to run from a tree that differs from its commit (git status: modified,
#                staged or untracked files, the report's own outputs left out); without it a dirty
#                tree is recorded and the report is marked "DIRTY TREE" at the top
# Environment: VISPACK_BENCH_VHP_SLICES (default "2 4 8"): slice counts of the vhp-size scaling
# runs; VISPACK_BENCH_MEDIUM=0 skips the medium phantom in the scaling runs;
# VISPACK_BENCH_MEM_SLICES (default "64 128 256"): slice counts of the per-stage memory runs;
# VISPACK_BENCH_STORE_SLICES (default 8): slices of the vhp phantom of the stored-size run;
# VISPACK_BENCH_OMEZARR_SLICES (default 128): slices of the vhp phantom of the OME-Zarr export run;
# VISPACK_BENCH_REAL_SLICES (default "128 256 512"): stack sizes of the real-size runs (2048x1216),
# VISPACK_BENCH_REAL_REPS (default 3): their one/two-thread and pack/zstd rounds.
# Results (JSON, logs) go to BUILD/bench/results; any failing benchmark makes the script exit 1.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
quick=0 report=1 do_build=1 require_clean=0 build=${VISPACK_BENCH_BUILD:-$root/build}
while [[ $# -gt 0 ]]; do
  case "$1" in
    --quick) quick=1 ;;
    --no-report) report=0 ;;
    --no-build) do_build=0 ;;
    --build) build=$(realpath -m "$2"); shift ;;
    --require-clean) require_clean=1 ;;
    --full-length) shift; exec "$root/scripts/bench/full_length.sh" --build "$build" --report "$@" ;;
    -h|--help) sed -n '2,21p' "$0"; exit 0 ;;
    *) echo "bench.sh: unknown option $1" >&2; exit 2 ;;
  esac
  shift
done
py=/usr/bin/python3
start=$(date +%s)
stamp() { printf '== [%4ds] %s\n' $(( $(date +%s) - start )) "$*"; }
fail() { echo "bench.sh: $*" >&2; exit 1; }

"$root/scripts/install-deps.sh" --bench >/dev/null || fail "scripts/install-deps.sh --bench failed"
for tool in elastix zstd gzip "$py"; do
  command -v "$tool" >/dev/null || fail "$tool is missing (scripts/install-deps.sh --bench)"
done
"$py" -c 'import numpy' 2>/dev/null || fail "python3-numpy is missing (scripts/install-deps.sh)"
if [[ $report == 1 ]]; then
  "$py" -c 'import matplotlib' 2>/dev/null || fail "python3-matplotlib is missing (scripts/install-deps.sh --bench)"
fi

if [[ $do_build == 1 ]]; then
  stamp "Building Release into $build"
  mkdir -p "$build"
  VISPACK_BUILD_TYPE=Release "$root/scripts/build.sh" "$build" >"$build/bench-build.log" 2>&1 || {
    tail -30 "$build/bench-build.log"; fail "build failed (log: $build/bench-build.log)"; }
fi
bin=$build/bin
for exe in vispack-phantom vispack-run vispack-register vispack-mask vispack-labels vispack-pack vispack-vdb \
  vispack-extract vispack-export vispack-info register_bench mask_bench ecc_bench; do
  [[ -x $bin/$exe ]] || fail "$bin/$exe was not built"
done

if [[ $quick == 1 ]]; then mode=quick; else mode=full; fi
work=$build/bench/$mode
res=$work/results
rm -rf "$res"
mkdir -p "$res" "$work/data"
export VISPACK_BENCH_MODE=$mode VISPACK_BENCH_RESULTS=$res VISPACK_BENCH_BIN=$bin VISPACK_BENCH_WORK=$work

# Machine, date and provenance (commit, dirty flag), for the report header.
"$py" "$root/scripts/bench/machine.py" >"$res/machine.json"
read -r commit dirty ndirty < <("$py" -c 'import json, sys; m = json.load(open(sys.argv[1]))
print(m["commit"], int(m["dirty"]), len(m["dirty_paths"]))' "$res/machine.json")
if [[ $dirty == 1 ]]; then
  [[ $require_clean == 1 ]] && fail "--require-clean: the tree differs from commit $commit in $ndirty path(s) (git status)"
  stamp "DIRTY TREE: numbers not reproducible from commit $commit (the report will say so)"
else
  stamp "Commit $commit, clean tree"
fi

# A phantom folder, generated once per build folder (the same options give the same bytes).
# A phantom folder is reused while its arguments and the generator that wrote it are the same
# (a rebuilt vispack-phantom may write another config or other slices: the folder is remade).
phantom_generator=$(sha256sum "$bin/vispack-phantom" | cut -c1-16)
phantom() {  # phantom NAME PRESET [SLICES [EXTRA FLAGS...]]
  local dir=$work/data/$1 args=(--preset "$2" --seed 1)
  [[ -n ${3:-} ]] && args+=(--slices "$3")
  [[ $# -gt 3 ]] && args+=("${@:4}")
  local key="${args[*]} generator $phantom_generator"
  if [[ ! -f $dir/.complete || "$(cat "$dir/.complete")" != "$key" ]]; then
    rm -rf "$dir"
    "$bin/vispack-phantom" --out "$dir" "${args[@]}" --quiet >"$res/phantom-$1.log" 2>&1 ||
      { cat "$res/phantom-$1.log"; fail "vispack-phantom $1 failed"; }
    echo "$key" >"$dir/.complete"
  fi
  echo "$dir"
}

if [[ $quick == 1 ]]; then
  reg_phantom=$(phantom tiny tiny); vol_phantom=$reg_phantom
  reg_pairs=2 reps=1 mask_slices=2 view_size=64 view_spv=1 view_reps=1 view_frames=1
else
  stamp "Generating phantoms (cached in $work/data)"
  # Registration pairs from a full-size stack without the black/duplicate slices, so every
  # consecutive pair is a usable drift measurement (the jump is still in it).
  # 23 slices: 22 pairs, 20 once the two beside the block jump are left out, enough that the
  # errors of vispack and elastix are not noise.
  reg_phantom=$(phantom vhp-reg vhp 23 --no-defects); vol_phantom=$(phantom small small)
  reg_pairs=20 reps=3 mask_slices=8 view_size=128 view_spv=0.5,1,2,4 view_reps=3 view_frames=3
fi

stamp "Registration: vispack methods and elastix on the same pairs, interleaved round by round"
rm -rf "$work/reg-dump" && mkdir -p "$work/reg-dump"
"$py" "$root/scripts/bench/register_peers.py" "$bin/register_bench" "$reg_phantom" $reg_pairs $reps \
  "$work/reg-dump" "$res/register.json" "$res/register_elastix.json" 2>"$res/register.log" ||
  { cat "$res/register.log"; fail "registration benchmark (register_bench, elastix) failed"; }

if [[ $quick == 0 ]]; then
  stamp "Registration on drift the solver's prior does not assume (heavy, rotation, bowed, 3..6 px jumps)"
  "$py" "$root/scripts/bench/drift_models.py" "$bin" "$work/drift-models" "$res/drift_models.json" \
    2>"$res/drift_models.log" || { cat "$res/drift_models.log"; fail "drift-model benchmark failed"; }
fi

stamp "ECC: OpenCV's findTransformECC against the fused iteration, same images, interleaved"
if [[ $quick == 1 ]]; then ecc_reps=1; else ecc_reps=9; fi
"$bin/ecc_bench" --reps $ecc_reps --json "$res/ecc.json" >"$res/ecc.log" 2>&1 ||
  { cat "$res/ecc.log"; fail "ecc_bench failed"; }

stamp "Mask: CT mask against the colour-threshold baseline"
"$bin/mask_bench" --slices $mask_slices --reps $reps --json "$res/mask.json" >"$res/mask.log" 2>&1 ||
  { cat "$res/mask.log"; fail "mask_bench failed"; }

stamp "Pipeline on $(basename "$vol_phantom"), then the pack sweep and its peers"
vol_name=$(basename "$vol_phantom")
/usr/bin/time -v "$bin/vispack-run" "$vol_phantom/config.json" --force --quiet \
  >"$res/run-$vol_name.log" 2>&1 || { tail -30 "$res/run-$vol_name.log"; fail "vispack-run failed"; }
"$py" "$root/scripts/bench/pack_sweep.py" "$vol_phantom" "$res/pack.json" || fail "pack sweep failed"

if [[ $quick == 0 ]]; then
  # Stored size against the OpenVDB export and zstd -3 of the raw level-0 bytes, and
  # the work folder against the input, at the real slice size. Recorded in docs/BENCHMARKS.md
  # ("Stored size and intermediates", written by the report from its results).
  stamp "Stored size and intermediates: vhp phantom, ${VISPACK_BENCH_STORE_SLICES:-8} slices"
  "$root/scripts/bench/store_size.sh" "$bin" "$work/store" "${VISPACK_BENCH_STORE_SLICES:-8}" \
    "$res/store_size.json" >"$res/store_size.md" 2>"$res/store_size.log" ||
    { cat "$res/store_size.log"; fail "stored-size benchmark failed"; }
  # The OME-Zarr export against vispack-extract writing NRRD, 2048x1216 (section "OME-Zarr
  # export against NRRD extraction", written by the report from its results).
  oz_slices=${VISPACK_BENCH_OMEZARR_SLICES:-128}
  stamp "OME-Zarr export against NRRD extraction: vhp phantom, $oz_slices slices, 3 rounds"
  "$root/scripts/bench/ome_zarr_export.sh" "$bin" "$work/ome-zarr" "$oz_slices" 2 \
    "$res/ome_zarr_export.json" 3 >"$res/ome_zarr_export.md" 2>"$res/ome_zarr_export.log" ||
    { cat "$res/ome_zarr_export.log"; fail "OME-Zarr export benchmark failed"; }
fi

stamp "Viewer: slice renderer and VTK's GPU ray caster on the same volume and view, interleaved"
if [[ -x $bin/viewer_bench ]]; then
  # Round by round, one viewer_bench process then one VTK process (A B A B ...), view_reps
  # rounds of view_frames timed frames each; quality = foreground PSNR against each one's fine
  # reference (scripts/bench/viewer_peers.py).
  "$py" "$root/scripts/bench/viewer_peers.py" "$bin" "$vol_phantom/out/volume.vpk" $view_size $view_spv \
    $view_reps $view_frames "$res" "$work" 2>"$res/viewer-driver.log" ||
    { tail -40 "$res/viewer.log"; cat "$res/viewer-driver.log"; fail "viewer benchmark (viewer_bench, VTK peer) failed"; }
else
  # Under CI (CI=true or VISPACK_STRICT=1) the viewer benchmark must run.
  [[ ${CI:-} == true || ${VISPACK_STRICT:-0} == 1 ]] &&
    fail "viewer_bench was not built: under CI the viewer benchmark must run"
  echo "bench.sh: viewer_bench not built (no viewer); skipping the viewer benchmark" | tee "$res/viewer.skipped"
fi

stamp "Cost as the work grows: whole pipeline time and peak memory"
if [[ $quick == 1 ]]; then
  scale_list="tiny:tiny:"
else
  scale_list="tiny:tiny: small:small:"
  [[ ${VISPACK_BENCH_MEDIUM:-1} == 1 ]] && scale_list+=" medium:medium:"
  for n in ${VISPACK_BENCH_VHP_SLICES:-2 4 8}; do scale_list+=" vhp-$n:vhp:$n"; done
fi
# Process start-up, measured apart (vispack-run --help: loads every library, does no work), so
# that the scaling fit can leave it out.
"$py" "$root/scripts/bench/startup.py" "$res/startup.json" 5 || fail "start-up timing failed"
if [[ $quick == 0 ]]; then
  # Every executable's start-up apart (`EXE --help`: libraries, relocations, CPU), for the
  # section "Process start-up per executable".
  "$py" "$root/scripts/bench/startup.py" --per-exe "$res/startup_per_exe.json" 5 "$bin" \
    >"$res/startup_per_exe.md" 2>"$res/startup_per_exe.log" ||
    { cat "$res/startup_per_exe.log"; fail "per-executable start-up timing failed"; }
fi
: >"$res/scaling.tsv"
for item in $scale_list; do
  IFS=: read -r name preset slices <<<"$item"
  dir=$(phantom "$name" "$preset" "$slices")
  [[ -f $res/run-$name.log ]] ||  # the volume phantom's run above counts as its row
  /usr/bin/time -v "$bin/vispack-run" "$dir/config.json" --force --quiet >"$res/run-$name.log" 2>&1 ||
    { tail -30 "$res/run-$name.log"; fail "vispack-run $name failed"; }
  "$py" "$root/scripts/bench/scaling_row.py" "$name" "$dir" "$res/run-$name.log" >>"$res/scaling.tsv"
  stamp "  $name: $(tail -1 "$res/scaling.tsv")"
done

if [[ $quick == 0 ]]; then
  # The whole pipeline on 2048x1216 stacks past several brick rows (one and two
  # threads, CPU per slice), the pack stage against zstd -3 -T2, and peak memory as they grow.
  real_slices=${VISPACK_BENCH_REAL_SLICES:-128 256 512}
  stamp "Whole pipeline at the real slice size: 2048x1216, $real_slices slices (ping-pong stacks of vhp-raw-64)"
  real_base=$(phantom vhp-raw-64 vhp 64 --rgb-raw)
  # shellcheck disable=SC2086  # the slice counts are separate arguments
  "$py" "$root/scripts/bench/real_size.py" "$real_base" "$res/real_size.json" $real_slices 2>"$res/real_size.log" ||
    { tail -30 "$res/real_size.log"; fail "real-size pipeline runs failed"; }
fi

stamp "Stages one by one: time per slice on 1 and 2 threads, error against truth"
if [[ $quick == 1 ]]; then stage_phantom=$(phantom tiny tiny); else stage_phantom=$(phantom vhp-8 vhp 8); fi
"$py" "$root/scripts/bench/stage_table.py" "$stage_phantom" "$res/stages.json" 2>"$res/stages.log" ||
  { cat "$res/stages.log"; fail "stage table failed"; }

stamp "Stages one by one: peak memory as the slice count grows"
# The writer holds up to ~two brick rows of 64 slices, so the counts must span several rows.
if [[ $quick == 1 ]]; then mem_list="24 48"; mem_preset=tiny; else mem_list=${VISPACK_BENCH_MEM_SLICES:-64 128 256}; mem_preset=small; fi
mem_dirs=()
for n in $mem_list; do mem_dirs+=("$(phantom "mem-$mem_preset-$n" "$mem_preset" "$n")"); done
"$py" "$root/scripts/bench/stage_memory.py" "$res/stage_memory.json" "${mem_dirs[@]}" 2>"$res/stage_memory.log" ||
  { cat "$res/stage_memory.log"; fail "stage memory runs failed"; }

if [[ -x $bin/format_bench ]]; then
  stamp "Format details: format_bench against libzstd in-process, interleaved (throughput, brick decode, writer memory)"
  if [[ $quick == 1 ]]; then fb_args=(--size 32 --sweep-size 32 --reps 1); else fb_args=(--size 128 --sweep-size 64 --reps 5); fi
  "$bin/format_bench" "${fb_args[@]}" --dir "$work/format-bench" >"$res/format_bench.md" 2>"$res/format_bench.log" ||
    { cat "$res/format_bench.log"; fail "format_bench failed"; }
fi

if [[ $quick == 0 ]]; then
  stamp "Profiles: where each stage spends its time (perf, else callgrind)"
  "$root/scripts/bench/profile.sh" "$vol_phantom" "$res/profile" || fail "profiling failed"
fi

if [[ $report == 1 ]]; then
  stamp "Writing docs/BENCHMARKS.md and docs/img/"
  "$py" "$root/scripts/bench/report.py" "$res" "$root/docs" || fail "report failed"
fi
stamp "bench.sh ($mode) finished; results in $res"

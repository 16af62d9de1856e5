#!/usr/bin/env bash
# Two runs on one work folder (pipeline/core/work_lock.h): a second run is refused at once with
# exit 7 and one line naming the folder and the holder's process id; a run that ended, or was
# killed (kill -9), leaves no lock behind; shards of disjoint slice ranges run side by side, while
# overlapping shards and a shard beside a whole run are refused.
# The first run is held at a known point with VISPACK_TEST_PAUSE (common/test_pause.h), so nothing
# depends on timing. Usage: work_lock.sh BIN_DIR
set -uo pipefail
bin=$(cd "$1" && pwd)
work=$(mktemp -d "${TMPDIR:-/tmp}/vispack-lock-XXXXXX")
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null; done
  rm -rf "$work"
}
trap cleanup EXIT
cd "$work" || exit 1
failed=0
fail() { echo "FAIL: $*"; failed=1; }

"$bin/vispack-phantom" --preset tiny --slices 6 --no-defects --quiet --out ph || exit 1
config=ph/config.json
lock_dir=$(cd ph && pwd)/work

# Starts vispack-run paused before its register stage (lock held); waits for the pause.
start_paused() {
  local flag=$work/paused-$1
  VISPACK_TEST_PAUSE="before:register@$flag" "$bin/vispack-run" "$config" --quiet \
    >"$work/first-$1.out" 2>"$work/first-$1.err" &
  pids+=($!)
  started=$!
  for _ in $(seq 1 2000); do [[ -e $flag ]] && return 0; sleep 0.01; done
  echo "the first run never reached its pause"; exit 1
}

# 1. A second vispack-run while the first holds the folder: exit 7, the first one's pid.
start_paused a
first=$started
"$bin/vispack-run" "$config" >second.out 2>second.err
rc=$?
expected="vispack-run: error: $lock_dir: work folder in use by another vispack run (process $first); wait for it to end, or give this run another work_dir"
[[ $rc == 7 ]] || fail "second vispack-run: exit $rc, expected 7"
[[ $(<second.err) == "$expected" ]] || fail "second vispack-run said: $(<second.err)"$'\n'"expected: $expected"
# A stage tool and a shard are refused too (a shard beside a whole run).
"$bin/vispack-mask" --config "$config" >stage.out 2>stage.err
rc=$?
[[ $rc == 7 && $(<stage.err) == *"(process $first)"* ]] || fail "vispack-mask beside a run: exit $rc: $(<stage.err)"
"$bin/vispack-register" --config "$config" --slices 0:3 >shard.out 2>shard.err
rc=$?
[[ $rc == 7 && $(<shard.err) == *"(process $first,"* ]] || fail "a shard beside a run: exit $rc: $(<shard.err)"
# The first run goes on and ends well; then the folder is free again.
rm -f "$work/paused-a"
wait "$first"
rc=$?
[[ $rc == 0 ]] || fail "the first run: exit $rc: $(<"$work/first-a.err")"
"$bin/vispack-run" "$config" --quiet >third.out 2>third.err
rc=$?
[[ $rc == 0 ]] || fail "a run after the first ended: exit $rc: $(<third.err)"

# 2. A run killed with kill -9 while holding the lock leaves the lock file, not the lock.
start_paused b
kill -9 "$started"
wait "$started" 2>/dev/null
[[ -e $lock_dir/.vispack.lock ]] || fail "no lock file in $lock_dir"
"$bin/vispack-run" "$config" --quiet >after-kill.out 2>after-kill.err
rc=$?
[[ $rc == 0 ]] || fail "a run after a killed one: exit $rc: $(<after-kill.err)"

# 3. Shards: one holding slices [0, 3) (as vispack-run --slices 0:3 locks: byte 0 shared, bytes
# [1, 4) exclusive, held here by python3's fcntl.lockf, the same record locks): a disjoint shard
# runs, an overlapping shard and a whole run are refused.
/usr/bin/python3 - "$lock_dir/.vispack.lock" "$work/held" <<'PY' &
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.lockf(fd, fcntl.LOCK_SH, 1, 0)
fcntl.lockf(fd, fcntl.LOCK_EX, 3, 1)
open(sys.argv[2], "w").close()
while os.path.exists(sys.argv[2]):
    time.sleep(0.01)
PY
holder=$!
pids+=($holder)
for _ in $(seq 1 2000); do [[ -e $work/held ]] && break; sleep 0.01; done
[[ -e $work/held ]] || { echo "the lock holder never started"; exit 1; }
"$bin/vispack-register" --config "$config" --slices 3:6 --quiet >disjoint.out 2>disjoint.err
rc=$?
[[ $rc == 0 ]] || fail "a disjoint shard: exit $rc: $(<disjoint.err)"
"$bin/vispack-register" --config "$config" --slices 2:4 --quiet >overlap.out 2>overlap.err
rc=$?
[[ $rc == 7 && $(<overlap.err) == *"(process $holder,"* ]] || fail "an overlapping shard: exit $rc: $(<overlap.err)"
"$bin/vispack-run" "$config" --quiet >whole.out 2>whole.err
rc=$?
[[ $rc == 7 && $(<whole.err) == *"(process $holder)"* ]] || fail "a whole run beside a shard: exit $rc: $(<whole.err)"
rm -f "$work/held"
wait "$holder"

[[ $failed == 0 ]] && echo "work lock: refused with the holder's pid, freed on exit and on kill -9, shards apart"
exit $failed

#!/usr/bin/python3
"""local_chain: the cluster chain of CONFIG (scripts/cluster_plan.py, the plan that
scripts/vispack-slurm submits) run on this machine without a scheduler: each step's array tasks
all at once as plain processes (one per shard, each with the plan's --threads), the next step when
the whole step has ended, as SLURM runs the chain on one node with a free CPU per task. It is how a
many-core machine without SLURM measures 1 -> 2 -> 4 -> 8 workers (docs/BENCHMARKS.md "On a
machine with a GPU and 16 cores"): the same commands, minus sbatch's per-job overhead (0.9 s a
job on the test cluster, docs/BENCHMARKS.md "Cluster").

Usage: local_chain.py CONFIG --bin DIR --shards N [--merge-threads M] [--json OUT]
Prints one line per step (tasks, wall seconds, the slowest task's seconds) and the chain's
wall seconds; --json OUT also writes them. Exit 0 when every task succeeded; 1 when one failed
(its command and the end of its output printed; the step's other tasks are stopped); 2 on a bad
argument or plan (cluster_plan's message).
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import cluster_plan  # noqa: E402  (scripts/cluster_plan.py)


def run_step(step, log_dir):
    """Runs the step's commands at once; returns (wall s, [task s]) or raises RuntimeError."""
    start = time.monotonic()
    running = []
    for i, argv in enumerate(step["commands"]):
        log = open(os.path.join(log_dir, f"{step['name']}-{i}.log"), "w+b")
        running.append((argv, log, subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT),
                        time.monotonic()))
    task_s = [0.0] * len(running)
    failed = None
    pending = set(range(len(running)))
    while pending:
        for i in sorted(pending):
            argv, log, proc, t0 = running[i]
            code = proc.poll()
            if code is None:
                continue
            pending.discard(i)
            task_s[i] = time.monotonic() - t0
            if code != 0 and failed is None:
                failed = (i, code)
        if failed is not None:
            break
        time.sleep(0.05)
    if failed is not None:
        for argv, log, proc, t0 in running:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        i, code = failed
        argv, log, proc, t0 = running[i]
        log.seek(0)
        tail = log.read().decode(errors="replace").splitlines()[-20:]
        raise RuntimeError(f"step {step['name']}, task {i}: exit {code}: {' '.join(argv)}\n"
                           + "\n".join("  " + line for line in tail))
    for _, log, _, _ in running:
        log.close()
    return time.monotonic() - start, task_s


def main(argv):
    parser = argparse.ArgumentParser(
        prog="local_chain.py",
        description="The vispack cluster chain of CONFIG run locally, each step's shards at once.")
    parser.add_argument("config")
    parser.add_argument("--bin", required=True, help="the folder of vispack-run and the stages")
    parser.add_argument("--shards", type=int, required=True, help="workers: tasks per step")
    parser.add_argument("--merge-threads", type=int,
                        help="vispack-merge's threads (default: the shards')")
    parser.add_argument("--json", help="also write the steps' times there")
    args = parser.parse_args(argv)
    try:
        plan = cluster_plan.make_plan(os.path.abspath(args.config), os.path.abspath(args.bin),
                                      shards=args.shards, merge_threads=args.merge_threads,
                                      node_cpus=lambda partition: os.cpu_count())
    except cluster_plan.PlanError as e:
        print(f"local_chain.py: {e}", file=sys.stderr)
        return 2
    steps = []
    start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="vispack-local-chain-") as log_dir:
        for step in plan["steps"]:
            try:
                wall, task_s = run_step(step, log_dir)
            except RuntimeError as e:
                print(f"local_chain.py: {e}", file=sys.stderr)
                return 1
            steps.append({"name": step["name"], "tasks": len(task_s), "wall_s": round(wall, 3),
                          "slowest_task_s": round(max(task_s), 3)})
            print(f"{step['name']}: {len(task_s)} task(s), {wall:.2f} s "
                  f"(slowest task {max(task_s):.2f} s)", flush=True)
    total = time.monotonic() - start
    print(f"chain: {args.shards} worker(s), {total:.2f} s")
    if args.json:
        with open(args.json + ".tmp", "w") as f:
            json.dump({"shards": args.shards, "bounds": plan["bounds"], "steps": steps,
                       "wall_s": round(total, 3)}, f, indent=1)
        os.replace(args.json + ".tmp", args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

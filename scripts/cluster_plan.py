#!/usr/bin/python3
"""cluster_plan: the vispack cluster chain of CONFIG as data, the one description that
scripts/vispack-slurm (its sbatch job scripts) and workflow/Snakefile (its rules) both follow.

Usage: cluster_plan.py CONFIG --bin DIR [--shards N] [--threads C] [--merge-threads M]
                       [--partition P] [--from STAGE] [--format json|sh] [--program NAME]

The chain, in order (a step runs when the whole step before it has ended):
  register-measure  array: vispack-register --slices A:B, with --records-only from 2 shards on
                    (no measure shard solves: each does the same work whichever ends last)
  slices            array: vispack-run --slices A:B --from FIRST --to LAST, the per-slice stages
                    of a shard in one process (register apply after solving the whole stack,
                    mask, labels; and pack when the shards are whole slabs)
  pack              array: vispack-pack --slices A:B, only when the shards are not whole slabs
  pack-merge        single: vispack-merge, with the merge threads (the shards' CPUs)
  vdb               array: vispack-vdb --slices A:B (each shard its part of the export)
Only the stages CONFIG enables (`vispack-run CONFIG --plan`) from --from on are in it. Array
task i takes stack indices [bounds[i], bounds[i+1]): whole slabs, [E*floor(i*L/N),
E*floor((i+1)*L/N)) capped at S, when there are at least N level-0 slabs (L = ceil(S/E), E =
pack_slab_slices); else [floor(i*S/N), floor((i+1)*S/N)) (so when `--plan` prints
pack_slab_slices 0: a colour file missing inside the stack makes slabs of output slices hold
fewer files, docs/ARCHITECTURE.md "Each input at its own z"). The merge threads default to N x C,
at most the CPUs of the largest node `sinfo` lists (for --partition), at least C.

Every command is `BIN/PROGRAM --config CONFIG ARGS --threads T --quiet` (vispack-run takes
CONFIG as its first argument). --format json (default) prints the plan with each step's
commands for every task; --format sh prints bash assignments for vispack-slurm (commands with
`$a:$b` for the task's slices). Python 3 standard library only; runs on the submitting machine
(or where Snakemake parses the Snakefile), never on the nodes.
Exit codes: 0, 2 usage or --from names a stage CONFIG does not enable, 3 CONFIG not found,
5 `vispack-run --plan` failed (CONFIG invalid or BIN wrong), 6 the stack has no slices.
"""
import argparse
import json
import os
import re
import shlex
import subprocess
import sys

STAGES = ("register", "mask", "labels", "pack", "vdb")
SLICES = "{slices}"  # the placeholder for a task's A:B in a step's argv


class PlanError(Exception):
    """A plan that cannot be made: the message names the file or option at fault."""

    def __init__(self, message, code):
        super().__init__(message)
        self.code = code


def pipeline_plan(bin_dir, config):
    """(slice count, slices per level-0 slab or 0, enabled stages) from `vispack-run --plan`."""
    run = os.path.join(bin_dir, "vispack-run")
    if not os.access(run, os.X_OK):
        raise PlanError(f"{run}: not found or not executable (bin)", 2)
    done = subprocess.run([run, config, "--plan"], capture_output=True, text=True)
    if done.returncode != 0:
        raise PlanError(f"{config}: vispack-run --plan failed: {done.stderr.strip()}", 5)
    fields = dict(line.split(" ", 1) for line in done.stdout.splitlines() if " " in line)
    slices = fields.get("slices", "").strip()
    if not slices.isdigit() or int(slices) == 0:
        raise PlanError(f"{config}: the stack has no slices", 6)
    slab = fields.get("pack_slab_slices", "").strip()
    return int(slices), int(slab) if slab.isdigit() else 0, fields.get("stages", "").split()


def largest_node_cpus(partition=None):
    """The CPUs of the largest node `sinfo` lists (for the partition), or None without sinfo."""
    try:
        done = subprocess.run(["sinfo", "-h", *(["-p", partition] if partition else []),
                               "-o", "%c"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    cpus = [int(d) for d in (re.sub(r"[^0-9]", "", line) for line in done.stdout.splitlines()) if d]
    return max(cpus) if done.returncode == 0 and cpus and max(cpus) > 0 else None


def shard_bounds(slices, shards, slab):
    """The N+1 stack indices that bound the shards, and whether the shards are whole slabs."""
    slabs = -(-slices // slab) if slab > 0 else 0
    if slabs >= shards:
        return [min(slices, i * slabs // shards * slab) for i in range(shards + 1)], True
    return [i * slices // shards for i in range(shards + 1)], False


OPTIONS = {"shards": "--shards", "threads": "--threads", "merge_threads": "--merge-threads",
           "first": "--from"}


def make_plan(config, bin_dir, shards=4, threads=1, merge_threads=None, first="register",
              partition=None, pipeline=None, node_cpus=largest_node_cpus, options=OPTIONS):
    """The chain as a dict (see the module's doc). pipeline: (slices, slab, stages) to use
    instead of asking vispack-run; node_cpus(partition): the merge's CPU cap, None if unknown;
    options: how errors name the arguments (the caller's option names)."""
    if first not in STAGES:
        raise PlanError(f"{options['first']} '{first}' is not a stage ({', '.join(STAGES)})", 2)
    for key, value in (("shards", shards), ("threads", threads), ("merge_threads", merge_threads)):
        if value is not None and (not isinstance(value, int) or value < 1):
            raise PlanError(f"{options[key]} '{value}' is not a positive integer", 2)
    config = os.path.abspath(config)
    bin_dir = os.path.abspath(bin_dir)
    slices, slab, enabled = pipeline or pipeline_plan(bin_dir, config)
    shards = min(shards, slices)
    bounds, aligned = shard_bounds(slices, shards, slab)
    if merge_threads is None:
        merge_threads = shards * threads
        cap = node_cpus(partition) if node_cpus else None
        if cap and cap < merge_threads:
            merge_threads = cap
        merge_threads = max(merge_threads, threads)

    steps = []
    per_slice = []

    def add(name, array, program, *args):
        steps.append({"name": name, "array": array, "program": program, "args": list(args),
                      "threads": threads if array else merge_threads})

    def add_per_slice():
        if per_slice:
            add("slices", True, "vispack-run", "--slices", SLICES, "--from", per_slice[0],
                "--to", per_slice[-1])
            per_slice.clear()

    chosen = [s for s in STAGES[STAGES.index(first):] if s in enabled]
    for stage in chosen:
        if stage == "vdb" or (stage == "pack" and not aligned):
            add_per_slice()
        if stage == "register":
            # No solve step: the slices step's register solves (vispack-slurm's header).
            add("register-measure", True, "vispack-register", "--slices", SLICES,
                *(["--records-only"] if shards > 1 else []))
            per_slice.append("register")
        elif stage in ("mask", "labels"):
            per_slice.append(stage)
        elif stage == "pack":
            if aligned:
                per_slice.append("pack")
                add_per_slice()
            else:
                add("pack", True, "vispack-pack", "--slices", SLICES)
            add("pack-merge", False, "vispack-merge")
        else:
            add("vdb", True, "vispack-vdb", "--slices", SLICES)
    add_per_slice()
    if not steps:
        raise PlanError(f"{options['first']} {first}: that stage is not enabled by {config}", 2)

    plan = {"config": config, "bin": bin_dir, "slices": slices, "pack_slab_slices": slab,
            "shards": shards, "whole_slabs": aligned, "bounds": bounds, "threads": threads,
            "merge_threads": merge_threads, "steps": steps}
    for number, step in enumerate(steps):
        step["after"] = steps[number - 1]["name"] if number else None
        step["argv"] = step_argv(plan, step)
        step["commands"] = [step_argv(plan, step, f"{a}:{b}")
                            for a, b in (zip(bounds, bounds[1:]) if step["array"] else [(0, 0)])]
    return plan


def step_argv(plan, step, slices=SLICES, threads=None):
    """A step's command for one task: slices (A:B) and threads replace the placeholders."""
    config = [plan["config"]] if step["program"] == "vispack-run" else ["--config", plan["config"]]
    args = [slices if a == SLICES else a for a in step["args"]]
    threads = step["threads"] if threads is None else threads
    return [os.path.join(plan["bin"], step["program"]), *config, *args,
            "--threads", str(threads), "--quiet"]


def shell_line(argv, raw=()):
    """argv as one shell command line: every word quoted except those in raw (placeholders)."""
    return " ".join(a if a in raw else shlex.quote(a) for a in argv)


def sh_assignments(plan):
    """The plan as bash assignments (vispack-slurm evaluates them)."""
    steps = plan["steps"]
    lines = [f"{k}={plan[k]}" for k in ("slices", "shards", "merge_threads")]
    lines.append(f"bounds=({' '.join(map(str, plan['bounds']))})")
    lines.append(f"step_names=({' '.join(s['name'] for s in steps)})")
    lines.append(f"step_kinds=({' '.join('array' if s['array'] else 'single' for s in steps)})")
    lines.append(f"step_threads=({' '.join(str(s['threads']) for s in steps)})")
    commands = (shell_line(step_argv(plan, s, "$a:$b"), ("$a:$b",)) for s in steps)
    lines.append(f"step_commands=({' '.join(shlex.quote(c) for c in commands)})")
    return "\n".join(lines)


def main(argv):
    parser = argparse.ArgumentParser(prog="cluster_plan.py", description=__doc__.split("\n")[0])
    parser.add_argument("config")
    parser.add_argument("--bin", required=True)
    parser.add_argument("--shards", type=int, default=4)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--merge-threads", type=int)
    parser.add_argument("--partition")
    parser.add_argument("--from", dest="first", default="register")
    parser.add_argument("--format", choices=("json", "sh"), default="json")
    parser.add_argument("--program", default="cluster_plan.py",
                        help="the name error messages start with")
    options = parser.parse_args(argv)
    try:
        if not os.path.isfile(options.config):
            raise PlanError(f"{options.config}: no such config file", 3)
        plan = make_plan(options.config, options.bin, options.shards, options.threads,
                         options.merge_threads, options.first, options.partition)
    except PlanError as error:
        print(f"{options.program}: error: {error}", file=sys.stderr)
        return error.code
    print(json.dumps(plan, indent=1) if options.format == "json" else sh_assignments(plan))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

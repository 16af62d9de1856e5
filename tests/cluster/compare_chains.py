#!/usr/bin/python3
"""Checks that vispack-slurm's job scripts and the Snakefile run the chain the planner
(scripts/cluster_plan.py) describes. Used by dry_run_test.sh.

Usage: compare_chains.py PLAN.json SLURM.txt [SNAKE.txt...]
  PLAN.json  cluster_plan.py's JSON
  SLURM.txt  one line per job script and array task, in chain and task order:
             STEP <tab> CPUS <tab> the command the task runs (shell words)
  SNAKE.txt  Snakemake's commands, one a line among other lines (the ones starting with the
             plan's bin folder), in the order it ran them: the output of `snakemake --dry-run
             --printshellcmds`, or the log of a run whose executables log their commands
The job scripts must run the planner's steps in order, each task its command with its CPUs; the
Snakemake jobs must be the planner's commands, each once, a step's only after the step before.
Prints what differs and exits 1, else exits 0.
"""
import json
import shlex
import sys


def main(plan_path, slurm_path, *snake_paths):
    plan = json.load(open(plan_path))
    expected = [(s["name"], s["threads"], c) for s in plan["steps"] for c in s["commands"]]
    errors = []

    slurm = []
    for line in open(slurm_path):
        name, cpus, command = line.rstrip("\n").split("\t")
        slurm.append((name, int(cpus), shlex.split(command)))
    if slurm != expected:
        errors.append("vispack-slurm's job scripts are not the planner's chain:")
        errors += [f"  planner: {e[0]} cpus {e[1]}: {shlex.join(e[2])}"
                   for e in expected if e not in slurm]
        errors += [f"  vispack-slurm: {e[0]} cpus {e[1]}: {shlex.join(e[2])}"
                   for e in slurm if e not in expected]
        if not errors[1:]:
            errors.append("  the same commands in another order")

    step_of = {tuple(c): n for n, s in enumerate(plan["steps"]) for c in s["commands"]}
    wanted = sorted(tuple(e[2]) for e in expected)
    for snake_path in snake_paths:
        snake = [shlex.split(line) for line in open(snake_path)
                 if line.startswith(plan["bin"] + "/")]
        if sorted(map(tuple, snake)) != wanted:
            errors.append(f"the Snakefile's jobs ({snake_path}) are not the planner's chain:")
            errors += [f"  planner: {shlex.join(c)}" for c in wanted if list(c) not in snake]
            errors += [f"  Snakefile: {shlex.join(c)}" for c in snake if tuple(c) not in step_of]
            if not errors[-1].startswith("  "):
                errors.append("  a command runs more or fewer times than the planner's")
        else:
            steps = [step_of[tuple(c)] for c in snake]
            if steps != sorted(steps):
                errors.append(f"the Snakefile ({snake_path}) runs a step before the step it "
                              "follows: " + " ".join(plan["steps"][n]["name"] for n in steps))
    print("\n".join(errors))
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))

"""Table (markdown) and plot of scripts/bench/pack_memory.sh's CSV.

usage: /usr/bin/python3 scripts/bench/pack_memory_plot.py pack_memory.csv OUT_DIR
Budget per row (docs/GOALS.md §6): dx * dy * edge * bytes per voxel (one level-0 brick row) + 300 MB.
Medians over repetitions; the plot needs matplotlib (a table only without it).
"""
import csv
import statistics
import sys
from collections import defaultdict

MIB = 1024.0 * 1024.0


def main():
    path, out = sys.argv[1], sys.argv[2]
    groups = defaultdict(list)
    for r in csv.DictReader(open(path)):
        groups[(r["binary"], int(r["edge"]), int(r["slices"]))].append(r)
    lines = ["| binary | brick edge | slices | peak RSS MiB | budget MiB (row + 300 MB) | "
             "peak / budget | CPU s (user+sys) | wall s | runs |",
             "|---|---|---|---|---|---|---|---|---|"]
    series = defaultdict(list)
    for (binary, edge, slices), rows in sorted(groups.items()):
        r0 = rows[0]
        row = int(r0["dx"]) * int(r0["dy"]) * edge * int(r0["bytes_per_voxel"])
        budget = (row + 300e6) / MIB
        peak = statistics.median(int(r["peak_rss_kib"]) / 1024.0 for r in rows)
        cpu = statistics.median(float(r["user_s"]) + float(r["sys_s"]) for r in rows)
        wall = statistics.median(float(r["wall_s"]) for r in rows)
        lines.append(f"| {binary} | {edge} | {slices} | {peak:.0f} | {budget:.0f} | "
                     f"{peak / budget:.2f} | {cpu:.1f} | {wall:.1f} | {len(rows)} |")
        series[(binary, edge)].append((slices, peak, budget))
    table = "\n".join(lines) + "\n"
    open(f"{out}/pack_memory.md", "w").write(table)
    print(table)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not found: table only")
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    for (binary, edge), pts in sorted(series.items()):
        pts.sort()
        xs = [p[0] for p in pts]
        line, = ax.plot(xs, [p[1] for p in pts], "o-", label=f"{binary}, edge {edge}")
        ax.plot(xs, [p[2] for p in pts], "--", color=line.get_color(), alpha=0.6,
                label=f"budget, edge {edge}" if binary == "current" else None)
    ax.set_xlabel("slices (2048 x 1216)")
    ax.set_ylabel("peak resident MiB")
    ax.set_title("vispack-pack peak memory against the slice count")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(f"{out}/pack_memory.png", dpi=100)


if __name__ == "__main__":
    main()

"""The one place the plotting backend is chosen (Agg), and helpers shared by the sections of the benchmark report (report.py): loading results, number
formatting, Markdown tables, plot styles and axes, and the log-log fit."""
import json
import math
import os

import numpy as np
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the sections draw through it)
import matplotlib.ticker  # noqa: E402

__all__ = ["OURS", "PEER", "fmt", "load", "loglog_fit", "matplotlib", "plain_ticks", "plt", "table"]

PEER = dict(color="crimson", marker="X", markersize=11, linestyle="--", linewidth=1.2)
OURS = dict(marker="o", linewidth=1.5)


def load(res, name):
    p = os.path.join(res, name)
    return json.load(open(p)) if os.path.exists(p) else None


def fmt(x, digits=3):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if abs(x) >= 100:
        return f"{x:,.0f}"
    if abs(x) >= 10:
        return f"{x:.1f}"
    return f"{x:.{digits}g}"


def table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def plain_ticks(ax, x=True, y=False):
    """Tick labels such as 20 and 0.05 on log axes instead of 2×10^1 and 5×10^-2."""
    f = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")

    def minor(v, _):  # label 2, 3 and 5 times a power of ten, leave the other minor ticks bare
        lead = f"{v:.0e}"[0]
        return f"{v:g}" if lead in "235" else ""

    for on, axis in ((x, ax.xaxis), (y, ax.yaxis)):
        if on:
            axis.set_major_formatter(f)
            axis.set_minor_formatter(matplotlib.ticker.FuncFormatter(minor))


def loglog_fit(x, y):
    """Least-squares slope and intercept of log y against log x."""
    lx, ly = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    a, b = np.polyfit(lx, ly, 1)
    return float(a), float(b)

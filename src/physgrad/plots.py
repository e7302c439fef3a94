"""Figures drawn from result files only (never from live training state)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def _curves(results: list[dict[str, Any]], method: str, split: str, metric: str):
    """Per seed: (wall_time, value) arrays of one method's metric, sorted by time."""
    by_seed: dict[str, list[tuple[float, float]]] = {}
    for r in results:
        if r["method"] == method and r["split"] == split and r["metric"] == metric:
            by_seed.setdefault(str(r["seed"]), []).append((float(r["wall_time"]), float(r["value"])))
    out = []
    for points in by_seed.values():
        t, v = np.array(sorted(points)).T
        keep = np.isfinite(v) & (v > 0)
        out.append((t[keep], v[keep]))
    return [c for c in out if c[0].size]


def loss_vs_time(
    results: list[dict[str, Any]],
    path: str | Path,
    *,
    order: Sequence[str],
    title: str = "",
    split: str = "test",
    metric: str = "loss",
    notes: dict[str, str] | None = None,
) -> Path:
    """Test loss vs training wall-clock, log y, one colour per method.

    The line is the geometric mean over seeds (mean of log10 loss, interpolated on a
    common time grid up to the shortest seed's end) and the band spans the seeds' minimum
    and maximum; a single seed is drawn as its own curve. ``notes`` adds text to a method's
    legend entry (e.g. how many of its runs diverged; their curves end where they diverged).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, method in enumerate(order):
        curves = _curves(results, method, split, metric)
        if not curves:
            continue
        colour = colours[i % len(colours)]
        extras = ([f"{len(curves)} seeds"] if len(curves) > 1 else []) + ([notes[method]] if notes and method in notes else [])
        label = f"{method} ({', '.join(extras)})" if extras else method
        if len(curves) == 1:
            ax.plot(*curves[0], color=colour, label=label, lw=1.5)
            continue
        end = min(t[-1] for t, _ in curves)
        grid = np.linspace(0.0, end, 200)
        logs = np.stack([np.interp(grid, t, np.log10(v)) for t, v in curves])
        ax.plot(grid, 10 ** logs.mean(0), color=colour, label=label, lw=1.5)
        ax.fill_between(grid, 10 ** logs.min(0), 10 ** logs.max(0), color=colour, alpha=0.2, lw=0)
    ax.set_yscale("log")
    ax.set_xlabel("training wall-clock time [s] (evaluation excluded)")
    ax.set_ylabel(f"{split} {metric}")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path

"""Figures drawn from result files only (never from live training state)."""

from __future__ import annotations

import math
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
    from matplotlib import rcParams
    from matplotlib.figure import Figure  # its own canvas: no pyplot, no backend switch

    fig = Figure(figsize=(7, 4.5), dpi=120)
    ax = fig.subplots()
    colours = rcParams["axes.prop_cycle"].by_key()["color"]
    for i, method in enumerate(order):
        curves = _curves(results, method, split, metric)
        if not curves:
            continue
        colour = colours[i % len(colours)]
        extras = ([f"{len(curves)} seeds"] if len(curves) > 1 else []) + (
            [notes[method]] if notes and method in notes else []
        )
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
    return path


LINE_STYLES = ("-", "--", ":", "-.")


def _moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over ``window`` points, left-padded with the first value."""
    if window <= 1 or values.size == 0:
        return values
    padded = np.concatenate([np.full(window - 1, values[0]), values])
    return np.convolve(padded, np.ones(window) / window, mode="valid")


def grid_panels(
    curves: list[tuple[dict[str, str], list[dict[str, Any]]]],
    path: str | Path,
    *,
    panel: str,
    methods: Sequence[str],
    metric: str = "test loss",
    title: str = "",
    smooth: int = 1,
) -> Path:
    """One panel per value of the ``panel`` setting (the StableBPTT figure layout): the
    ``metric`` against epochs, log y; colour = method, line style = the cell's other swept
    settings. Each line is the geometric mean over seeds (on the epochs all seeds reached),
    after a ``smooth``-point moving average left-padded with the first value (as the
    authors' plots). ``curves`` holds (cell, metric rows with an ``epoch`` field) per cell."""
    from matplotlib import rcParams
    from matplotlib.figure import Figure  # its own canvas: no pyplot, no backend switch

    values = list(dict.fromkeys(cell[panel] for cell, _ in curves))
    others = list(dict.fromkeys(tuple((k, v) for k, v in cell.items() if k != panel) for cell, _ in curves))
    colours = rcParams["axes.prop_cycle"].by_key()["color"]
    fig = Figure(figsize=(4.2 * max(len(values), 1), 3.8), dpi=120)
    axes = fig.subplots(1, max(len(values), 1), squeeze=False, sharey=True)
    for ax, value in zip(axes[0], values):
        for cell, rows in curves:
            if cell[panel] != value:
                continue
            rest = tuple((k, v) for k, v in cell.items() if k != panel)
            style = LINE_STYLES[others.index(rest) % len(LINE_STYLES)]
            for i, method in enumerate(methods):
                by_seed: dict[str, list[tuple[float, float]]] = {}
                for r in rows:
                    if r["method"] == method:
                        by_seed.setdefault(r["seed"], []).append((r["epoch"], float(r["value"])))
                series = [np.array(sorted(p)).T for p in by_seed.values() if p]
                if not series:
                    continue
                n = min(s.shape[1] for s in series)
                epochs = series[0][0][:n]
                logs = np.stack([np.log10(np.maximum(_moving_average(s[1][:n], smooth), 1e-30)) for s in series])
                label = method + (f" ({', '.join(f'{k}={v}' for k, v in rest)})" if rest else "")
                ax.plot(epochs, 10 ** logs.mean(0), style, color=colours[i % len(colours)], lw=1.2, label=label)
        ax.set_yscale("log")
        ax.set_title(f"{panel} = {value}", fontsize=9)
        ax.set_xlabel("epoch")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel(metric)
    legend = {}  # every panel's lines (a panel of a partly finished grid may have none)
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    labels = list(legend)
    if labels:
        fig.legend(
            list(legend.values()), labels, loc="lower center", ncol=min(len(labels), 4), fontsize=7, frameon=False
        )
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.04 + 0.035 * math.ceil(len(labels) / 4), 1, 0.95))
    path = Path(path)
    fig.savefig(path)
    return path

"""Figures drawn from result files only (never from live training state).

A figure never loses a study: values a log axis cannot show (NaN, infinities, losses that
overflow towards 1e308 when a run diverges) are clipped to the axis range and marked with
an ``x`` at its edge, and :func:`draw` turns any failure into a :class:`FigureWarning`
(the tables are written before any figure is drawn)."""

from __future__ import annotations

import math
import textwrap
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..engine import rundir

# The widest log range a figure shows: beyond it matplotlib's log ticks overflow, and no
# training curve needs it. Above the curves' highest starting value a figure shows at most
# DECADES_ABOVE_START decades: a diverging run's values beyond that are clipped and marked.
LOG_LIMITS = (1e-200, 1e200)
DECADES_ABOVE_START = 3
MARK_LABEL = "x: diverged or off-scale, drawn at the axis edge"


class FigureWarning(UserWarning):
    """A figure could not be drawn; the study's tables and CSV files are complete."""


def save_figure(fig, path: str | Path, **options) -> None:
    """``fig.savefig`` through :func:`physgrad.engine.rundir.atomic_file`: a kill or a failed write
    leaves the previous figure whole, never an empty or half-written PNG."""
    path = Path(path)
    with rundir.atomic_file(path) as f:
        fig.savefig(f, format=path.suffix.lstrip(".") or "png", **options)


def draw(make: Callable[..., Path], *args: Any, **kwargs: Any) -> Path | None:
    """``make(*args, **kwargs)`` (a figure function such as :func:`loss_vs_time`), or None
    and one :class:`FigureWarning` line if drawing fails: a figure is never worth a study."""
    try:
        return make(*args, **kwargs)
    except Exception as e:  # noqa: BLE001 — any failure of a figure is only a warning
        target = kwargs.get("path", args[1] if len(args) > 1 else "")
        text = " ".join(f"{type(e).__name__}: {e}".split())
        warnings.warn(f"figure {target} not drawn ({text}); the tables are complete", FigureWarning, stacklevel=2)
        return None


def log_range(series: Sequence[np.ndarray]) -> tuple[float, float]:
    """The y range of a log-scaled figure of ``series``: from the smallest positive finite
    value to the largest, but at most :data:`DECADES_ABOVE_START` decades above the
    highest first value of a series, and within :data:`LOG_LIMITS`."""
    values = [np.asarray(v, dtype=float) for v in series]
    shown = [v[np.isfinite(v) & (v > 0)] for v in values]
    finite = np.concatenate(shown) if shown else np.zeros(0)
    if not finite.size:
        return 1e-3, 1.0
    starts = [v[0] for v in shown if v.size]
    ceiling = 10.0 ** (math.ceil(math.log10(max(starts))) + DECADES_ABOVE_START)
    upper = min(float(finite.max()), ceiling, LOG_LIMITS[1])
    lower = min(max(float(finite.min()), LOG_LIMITS[0]), upper)
    if lower >= upper:
        lower, upper = lower / 10, upper * 10
    return lower, upper


def clip_marks(t: np.ndarray, v: np.ndarray, lower: float, upper: float):
    """``(t, v)`` on a log axis from ``lower`` to ``upper``: non-positive values dropped,
    values outside the range clipped to it; also the (time, edge value) of every point
    that was not finite or was clipped (drawn as an ``x`` at the edge)."""
    t, v = np.asarray(t, dtype=float), np.asarray(v, dtype=float)
    keep = ~(np.isfinite(v) & (v <= 0))  # a log axis cannot show zero or negative values
    t, v = t[keep], v[keep]
    high = ~np.isfinite(v) | (v > upper)  # NaN and ±inf: the run left the range (diverged)
    low = np.isfinite(v) & (v < lower)
    edge = np.where(high, upper, lower)
    marked = high | low
    clipped = np.where(marked, edge, v)
    return t, clipped, (t[marked], edge[marked])


def calibrated_axis(results: list[dict[str, Any]]) -> bool:
    """Whether the rows carry the calibrated time (a calibrated study's ``results.csv``,
    :mod:`physgrad.harness.calibration`)."""
    return any(r.get("calibrated_time") not in (None, "") for r in results)


def row_time(r: dict[str, Any], calibrated: bool) -> float:
    """A row's time on the figure's axis: the calibrated time where the axis is calibrated
    and the row has one, else the training wall-clock."""
    value = r.get("calibrated_time") if calibrated else None
    return float(value if value not in (None, "") else r["wall_time"])


def _series(results: list[dict[str, Any]], method: str, split: str, metric: str, calibrated: bool = False):
    """Per seed: (seed, time, value) of one method's metric, sorted by time (every value,
    NaN and infinities included); the time is :func:`row_time`'s."""
    by_seed: dict[str, list[tuple[float, float]]] = {}
    for r in results:
        if r["method"] == method and r["split"] == split and r["metric"] == metric:
            by_seed.setdefault(str(r["seed"]), []).append((row_time(r, calibrated), float(r["value"])))
    return [(seed, *np.array(sorted(points, key=lambda p: p[0])).T) for seed, points in by_seed.items() if points]


def _mark_legend(ax) -> None:
    from matplotlib.lines import Line2D

    handles, labels = ax.get_legend_handles_labels()
    handles.append(Line2D([], [], ls="", marker="x", color="0.3"))
    labels.append(MARK_LABEL)
    ax.legend(handles, labels, fontsize=8)


def failure_median(logs: np.ndarray, upper: float) -> np.ndarray:
    """The median over seeds (axis 0) of log values in which a diverged seed is +∞ from its
    end on, as in the tables: for an even count the mean of the two middle values, which is
    +∞ (drawn at ``upper``, the axis's top) once a middle seed diverged, never a value
    between the survivor and the failure."""
    return np.minimum(np.median(logs, axis=0), math.log10(upper))


def seed_median(curves: Sequence[tuple[np.ndarray, np.ndarray, bool]], upper: float):
    """(grid, median) over seeds (:func:`failure_median`) of curves (t, v, diverged) already
    on the axis range: a diverged seed counts as +∞ from its end on (drawn at ``upper``, the
    top of the axis), so the median never averages over a divergence and is at the top once
    half the seeds diverged.
    The grid runs to the end of the shortest finished seed (the longest diverged one if all
    diverged); None if no curve."""
    if not curves:
        return None
    finished = [t[-1] for t, _, failed in curves if not failed]
    end = min(finished) if finished else max(t[-1] for t, _, _ in curves)
    grid = np.linspace(0.0, end, 200)
    logs = []
    for t, v, failed in curves:
        log = np.interp(grid, t, np.log10(v))
        if failed:
            log = np.where(grid > t[-1], math.inf, log)
        logs.append(log)
    return grid, 10 ** failure_median(np.stack(logs), upper)


def loss_vs_time(
    results: list[dict[str, Any]],
    path: str | Path,
    *,
    order: Sequence[str],
    title: str = "",
    split: str = "test",
    metric: str = "loss",
    notes: dict[str, str] | None = None,
    diverged: dict[str, set[str]] | None = None,
) -> Path:
    """Test loss vs training time, log y, one colour per method: the calibrated time
    (step × calibrated seconds per step) where the rows carry it, else the training
    wall-clock.

    Each seed is drawn as its own thin curve; with several seeds the thick line is the
    median over seeds (:func:`seed_median`: a diverged seed counts as the top of the axis
    from where it diverged, never averaged away). A seed in ``diverged`` (``{method:
    seeds}``) ends with an ``x`` at the top edge, as do its non-finite and off-scale values.
    ``notes`` adds text to a method's legend entry (e.g. how many of its runs diverged).
    """
    from matplotlib import rcParams
    from matplotlib.figure import Figure  # its own canvas: no pyplot, no backend switch

    fig = Figure(figsize=(7, 4.5), dpi=120)
    ax = fig.subplots()
    colours = rcParams["axes.prop_cycle"].by_key()["color"]
    calibrated = calibrated_axis(results)
    series = {method: _series(results, method, split, metric, calibrated) for method in order}
    lower, upper = log_range([v for runs in series.values() for _, _, v in runs])
    failed = diverged or {}
    marked = False
    for i, method in enumerate(order):
        curves, marks = [], []
        for seed, t, v in series[method]:
            t, v, mark = clip_marks(t, v, lower, upper)
            if not t.size:
                continue
            lost = seed in failed.get(method, ())
            curves.append((t, v, lost))
            marks.append(mark)
            if lost:  # where it diverged: the end of its curve, at the top edge
                marks.append((t[-1:], np.array([upper])))
        if not curves:
            continue
        colour = colours[i % len(colours)]
        extras = ([f"{len(curves)} seeds"] if len(curves) > 1 else []) + (
            [notes[method]] if notes and method in notes else []
        )
        label = f"{method} ({', '.join(extras)})" if extras else method
        for mt, mv in marks:
            if mt.size:
                ax.plot(mt, mv, "x", color=colour, ms=7, mew=1.5, clip_on=False)
                marked = True
        if len(curves) == 1:
            ax.plot(*curves[0][:2], color=colour, label=label, lw=1.5)
            continue
        for t, v, _ in curves:
            ax.plot(t, v, color=colour, lw=0.7, alpha=0.45)
        median = seed_median(curves, upper)
        if median is not None:
            ax.plot(*median, color=colour, label=label, lw=1.8)
    ax.set_ylim(lower / 1.5, upper * 1.5)
    ax.set_yscale("log")
    ax.set_xlabel("calibrated training time [s] (step × calibrated s/step)" if calibrated
                  else "training wall-clock time [s] (evaluation excluded)")  # fmt: skip
    ax.set_ylabel(f"{split} {metric} (thin: each seed; thick: median over seeds)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    if marked:
        _mark_legend(ax)
    elif ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path)
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
    settings. Each line is the median over seeds (:func:`failure_median`; on the epochs every finished seed reached;
    a seed whose rows say ``diverged`` counts as the top edge from its end on, marked with an
    ``x`` where it diverged), after a ``smooth``-point moving average left-padded with the
    first value (as the authors' plots). ``curves`` holds (cell, metric rows with an ``epoch`` field) per cell."""
    from matplotlib import rcParams
    from matplotlib.figure import Figure  # its own canvas: no pyplot, no backend switch

    values = list(dict.fromkeys(cell[panel] for cell, _ in curves))
    others = list(dict.fromkeys(tuple((k, v) for k, v in cell.items() if k != panel) for cell, _ in curves))
    colours = rcParams["axes.prop_cycle"].by_key()["color"]
    fig = Figure(figsize=(4.2 * max(len(values), 1), 3.8), dpi=120)
    axes = fig.subplots(1, max(len(values), 1), squeeze=False, sharey=True)
    # Per cell and method: each seed's (epochs, values), sorted by epoch.
    seeds: dict[tuple[int, str], list[np.ndarray]] = {}
    failed: dict[tuple[int, str], list[bool]] = {}  # per seed: whether it diverged (its rows say "diverged")
    lost: set[tuple[int, str, str]] = set()
    for c, (_, rows) in enumerate(curves):
        for method in methods:
            by_seed: dict[str, list[tuple[float, float]]] = {}
            for r in rows:
                if r["method"] == method:
                    by_seed.setdefault(r["seed"], []).append((r["epoch"], float(r["value"])))
                    if r.get("diverged"):
                        lost.add((c, method, r["seed"]))
            seeds[c, method] = [np.array(sorted(p, key=lambda q: q[0])).T for p in by_seed.values() if p]
            failed[c, method] = [(c, method, seed) in lost for seed, p in by_seed.items() if p]
    lower, upper = log_range([s[1] for series in seeds.values() for s in series])
    marked = False
    for ax, value in zip(axes[0], values):
        for c, (cell, _) in enumerate(curves):
            if cell[panel] != value:
                continue
            rest = tuple((k, v) for k, v in cell.items() if k != panel)
            style = LINE_STYLES[others.index(rest) % len(LINE_STYLES)]
            for i, method in enumerate(methods):
                series, lost_seed = seeds[c, method], failed[c, method]
                if not series:
                    continue
                # to the shortest finished seed; a diverged seed counts as the top edge after its end
                n = min(
                    (s.shape[1] for s, f in zip(series, lost_seed) if not f), default=max(s.shape[1] for s in series)
                )
                longest = max(series, key=lambda s: s.shape[1])
                epochs = longest[0][:n]
                colour = colours[i % len(colours)]
                logs = []
                for s, f in zip(series, lost_seed):  # NaN, infinite and off-scale values at the axis edge, marked
                    values, end = s[1][:n], s[1][:n].size
                    if f and values.size < n:
                        values = np.concatenate([values, np.full(n - values.size, math.inf)])
                    high = ~np.isfinite(values) | (values > upper)
                    clipped = np.clip(np.where(high, upper, values), lower, upper)
                    log = np.log10(np.clip(_moving_average(clipped, smooth), lower, upper))
                    log[end:] = math.inf  # a diverged seed from its end on: a failure in the median
                    logs.append(log)
                    if high.any():
                        first = int(np.argmax(high)) if f and s[1].size < n else None
                        at = epochs[high] if first is None else epochs[first : first + 1]
                        ax.plot(at, np.full(at.size, upper), "x", color=colour, ms=6, clip_on=False)
                        marked = True
                label = method + (f" ({', '.join(f'{k}={v}' for k, v in rest)})" if rest else "")
                ax.plot(epochs, 10 ** failure_median(np.stack(logs), upper), style, color=colour, lw=1.2, label=label)
        ax.set_ylim(lower / 1.5, upper * 1.5)
        ax.set_yscale("log")
        ax.set_title(f"{panel} = {value}", fontsize=9)
        ax.set_xlabel("epoch")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel(metric)
    legend = {}  # every panel's lines (a panel of a partly finished grid may have none)
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    if marked:
        from matplotlib.lines import Line2D

        legend[MARK_LABEL] = Line2D([], [], ls="", marker="x", color="0.3")
    labels = list(legend)
    # a one-panel figure is narrow: fewer legend columns, and the title wrapped to its width
    # (≈ 13 characters per inch at 10 pt), so neither runs off the edges
    width = fig.get_figwidth()
    ncol = max(1, min(len(labels), 4, int(width / 1.6)))
    if labels:
        fig.legend(list(legend.values()), labels, loc="lower center", ncol=ncol, fontsize=7, frameon=False)
    title_lines = textwrap.wrap(title, width=int(13 * width)) or [""]
    fig.suptitle("\n".join(title_lines), fontsize=10)
    top = 0.95 - 0.045 * (len(title_lines) - 1)
    fig.tight_layout(rect=(0, 0.04 + 0.035 * math.ceil(len(labels) / ncol), 1, top))
    path = Path(path)
    save_figure(fig, path)
    return path


def heatmap(
    tables: dict[str, Sequence[dict[str, Any]]],
    path: str | Path,
    *,
    reference: str,
    clip: tuple[float, float],
    title: str = "",
) -> Path:
    """Method × problem heat map of log₁₀(mean final test loss / the ``reference``'s) from
    the bench's tables (``{problem: physgrad.harness.bench.method_rows(...)}``): blue below the
    reference, red above; the ratio is written in each cell (``†``: some seeds diverged or
    failed). Ratios enter the logarithm clipped to ``clip`` (a loss of exactly 0 has ratio
    0). Cells whose runs all diverged or failed are grey, hatched and crossed; methods that
    do not apply (or were skipped, or have not run) are blank; ``n/a``: ran, but the
    reference has no result to compare with."""
    from matplotlib.figure import Figure  # its own canvas: no pyplot, no backend switch
    from matplotlib.patches import Rectangle

    problems = list(tables)
    methods = list(dict.fromkeys(t["method"] for table in tables.values() for t in table
                                 if t["status"] not in ("not applicable", "skipped")))  # fmt: skip
    cell = {(p, t["method"]): t for p, table in tables.items() for t in table}
    values = np.full((len(methods), len(problems)), np.nan)
    for i, m in enumerate(methods):
        for j, p in enumerate(problems):
            t = cell.get((p, m))
            if t and not math.isnan(t["ratio"]):  # +∞: a failure on at least half the seeds, saturated
                values[i, j] = math.log10(min(max(t["ratio"], clip[0]), clip[1]))
    finite = values[np.isfinite(values)]
    limit = min(max(1.0, float(np.abs(finite).max()) if finite.size else 1.0), 4.0)  # beyond ±4: saturated
    fig = Figure(figsize=(1.5 + 0.9 * max(len(problems), 1), 1.2 + 0.4 * max(len(methods), 1)), dpi=120)
    ax = fig.subplots()
    image = ax.imshow(np.ma.masked_invalid(values), cmap="RdBu_r", vmin=-limit, vmax=limit, aspect="auto")
    for i, m in enumerate(methods):
        for j, p in enumerate(problems):
            t = cell.get((p, m))
            if t is None or t["status"] in ("not applicable", "skipped", "pending"):
                continue
            if t["status"] in ("diverged", "failed"):
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, facecolor="0.85", hatch="xx", edgecolor="0.5", lw=0))
                ax.text(
                    j, i, "diverged" if t["status"] == "diverged" else "failed", ha="center", va="center", fontsize=6
                )
            elif np.isfinite(values[i, j]):
                mark = "†" if t["diverged"] or t["failed"] else ""
                ax.text(j, i, f"{t['ratio']:.2g}{mark}", ha="center", va="center", fontsize=6,
                        color="white" if abs(values[i, j]) > 0.6 * limit else "black")  # fmt: skip
            else:
                ax.text(j, i, "n/a", ha="center", va="center", fontsize=6, color="0.4")
    ax.set_xticks(range(len(problems)), problems, rotation=45, ha="right", fontsize=7)
    ax.set_yticks(range(len(methods)), methods, fontsize=7)
    ax.set_xlim(-0.5, len(problems) - 0.5)
    ax.set_ylim(len(methods) - 0.5, -0.5)
    bar = fig.colorbar(image, ax=ax, fraction=0.05, pad=0.02)
    bar.set_label(f"log10(final test loss / {reference}'s)", fontsize=7)
    bar.ax.tick_params(labelsize=6)
    ax.set_title(title or f"final test loss relative to {reference} (blue: lower; blank: not applicable)", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path)
    return path


def performance_profile(
    taus: Sequence[float], rho: dict[str, Sequence[float]], path: str | Path, *, title: str = ""
) -> Path:
    """A Dolan–Moré performance profile (:mod:`physgrad.harness.targets`): per method the
    fraction of problems ρ(τ) whose time-to-target is within τ of the fastest method's,
    a step function of τ on a log axis."""
    from matplotlib import rcParams
    from matplotlib.figure import Figure  # its own canvas: no pyplot, no backend switch

    fig = Figure(figsize=(7, 4.5), dpi=120)
    ax = fig.subplots()
    colours = rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ("-", "--", ":", "-.")
    for i, (method, values) in enumerate(rho.items()):
        ax.step(list(taus), list(values), where="post", label=method, color=colours[i % len(colours)],
                ls=styles[(i // len(colours)) % len(styles)], lw=1.6)  # fmt: skip
    ax.set_xscale("log")
    ax.set_xlim(1.0, max(taus) if len(taus) else 10.0)
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("τ: time-to-target within a factor τ of the fastest method (log)")
    ax.set_ylabel("fraction of problems ρ(τ)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    if rho:
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path)
    return path

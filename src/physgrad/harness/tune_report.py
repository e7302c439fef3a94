"""A tune directory's table and figures, redrawn from its files alone (``physgrad report DIR``).

From ``tune.json`` and ``trials.csv`` (:mod:`physgrad.harness.tune`): one table row per
method (trials run, pruned and failed, the untuned trial's validation loss, the best one
and its hyperparameters beside the untuned values, and the chosen configuration's test
loss over seeds from ``final/summary.csv``), and ``trials.png``: one row of panels per
method, the validation loss of every trial against each searched hyperparameter (log
axes; the untuned trial as a square, the chosen one as a star, pruned trials hollow at the
loss of their last rung, failed or diverged ones as crosses on the top edge). This is the
figure of a hyperparameter sweep in "Fantastic pretraining optimizers" (Wen et al. 2025,
loss against learning rate per optimizer): it shows whether the optimum lies inside the
searched range or at its edge.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import ConfigError
from .plots import draw, save_figure
from .seeds import aggregate, median_cell
from .study import kept_path, read_csv


class TuneReport(NamedTuple):
    """The table's printable lines and the figure's path (None: not drawn, a warning says why)."""

    lines: list[list[str]]
    figure: Path | None


def _number(text: Any) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def read_trials(out: str | Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """``tune.json`` and the rows of ``trials.csv`` (``params`` parsed, ``val_loss`` a number)."""
    out = Path(out)
    if not (out / "tune.json").exists() or not kept_path(out / "trials.csv").exists():
        raise ConfigError(f"{out} is not a tune directory: tune.json or trials.csv is missing")
    info = json.loads((out / "tune.json").read_text())
    rows = read_csv(out / "trials.csv")
    for r in rows:
        r["params"] = json.loads(r["params"] or "{}")
        r["val_loss"] = _number(r["val_loss"])
        r["trial"] = int(r["trial"])
    return info, rows


def chosen(rows: list[dict[str, Any]], method: str) -> dict[str, Any] | None:
    """The method's selected trial: the COMPLETE one with the lowest validation loss."""
    done = [r for r in rows if r["method"] == method and r["state"] == "COMPLETE" and math.isfinite(r["val_loss"])]
    return min(done, key=lambda r: (r["val_loss"], r["trial"])) if done else None


def table(out: str | Path) -> list[list[str]]:
    """The per-method table (header first)."""
    out = Path(out)
    info, rows = read_trials(out)
    final = {}
    if kept_path(out / "final" / "summary.csv").exists():
        summary = read_csv(out / "final" / "summary.csv")
        final = {t["method"]: t for t in aggregate(summary, info["methods"])}
    head = ["method", "trials (pruned, failed)", "untuned val loss", "best val loss", "chosen hyperparameters",
            "untuned values", "test loss of the chosen: median [95% CI]"]  # fmt: skip
    lines = [head]
    for method in info["methods"]:
        mine = [r for r in rows if r["method"] == method]
        states = [r["state"] for r in mine]
        untuned = next((r for r in mine if r["trial"] == 0), None)
        best = chosen(rows, method)
        defaults = info.get("defaults", {}).get(method, {})
        lines.append([
            method, f"{len(mine)} ({states.count('PRUNED')}, {states.count('FAIL')})",
            f"{untuned['val_loss']:.3e}" if untuned and math.isfinite(untuned["val_loss"]) else "-",
            f"{best['val_loss']:.3e}" if best else "-",
            ", ".join(f"{k}={v:.3g}" for k, v in best["params"].items()) if best else "none finished",
            ", ".join(f"{k}={v:.3g}" for k, v in defaults.items()),
            median_cell(final[method]["final"]) if method in final else "-",
        ])  # fmt: skip
    return lines


def trials_figure(out: str | Path, path: str | Path | None = None) -> Path:
    """``trials.png``: validation loss against each searched hyperparameter, one row per method."""
    from matplotlib.figure import Figure

    out = Path(out)
    info, rows = read_trials(out)
    methods = [m for m in info["methods"] if any(r["method"] == m for r in rows)]
    width = max((len(info["spaces"].get(m, {})) for m in methods), default=1) or 1
    fig = Figure(figsize=(3.6 * width, 2.8 * max(len(methods), 1)), layout="constrained")
    axes = np.atleast_2d(fig.subplots(max(len(methods), 1), width, squeeze=False))
    finite = [r["val_loss"] for r in rows if math.isfinite(r["val_loss"]) and r["val_loss"] > 0]
    top = max(finite) * 2 if finite else 1.0
    for i, method in enumerate(methods):
        mine = [r for r in rows if r["method"] == method]
        best = chosen(rows, method)
        names = list(info["spaces"].get(method, {}))
        for j in range(width):
            ax = axes[i, j]
            if j >= len(names):
                ax.set_visible(False)
                continue
            name = names[j]
            for r in mine:
                x, y = r["params"].get(name), r["val_loss"]
                if x is None:
                    continue
                failed = r["state"] == "FAIL" or not math.isfinite(y)
                style = dict(marker="x", color="tab:red") if failed else dict(
                    marker="s" if r["trial"] == 0 else "o", color="tab:blue",
                    facecolors="none" if r["state"] == "PRUNED" else "tab:blue")  # fmt: skip
                ax.scatter([x], [top if failed else y], s=28, **style)
            if best is not None and name in best["params"]:
                ax.scatter([best["params"][name]], [best["val_loss"]], marker="*", s=160, color="tab:orange", zorder=3)
            low, high = info.get("bounds", {}).get(method, {}).get(name, (None, None))
            if low and high:  # the searched range: is the optimum inside it or at its edge?
                ax.set_xlim(low / 1.5, high * 1.5)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(f"{name}  ({info['spaces'][method][name]})", fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{method}\nvalidation loss")
    fig.suptitle(f"{info['problem']}: {info['trials']} trials per method, {_budget(info)} each "
                 "(square: untuned; star: chosen; hollow: pruned; x: failed)", fontsize=9)  # fmt: skip
    path = Path(path or out / "trials.png")
    save_figure(fig, path, dpi=110)
    return path


def _budget(info: dict[str, Any]) -> str:
    return ", ".join(f"{v:g} {k}" for k, v in info.get("budget", {}).items())


def report(out: str | Path) -> TuneReport:
    """The table and ``trials.png`` of a tune directory, from its files alone."""
    lines = table(out)
    return TuneReport(lines, draw(trials_figure, out, Path(out) / "trials.png"))


__all__ = ["TuneReport", "chosen", "read_trials", "report", "table", "trials_figure"]

"""The reproduction reports' Markdown (docs/reproductions/): one or more studies' tables and
figures as a section of a page, and the per-seed final values they quote."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..seeds import aggregate, format_table, mean_std, median_cell, summarize
from .tables import diverged_seeds, read_csv


def load_studies(root: str | Path, parts: Sequence[tuple[str, str]]):
    """Summary rows, metric rows and method order of one or more studies under ``root``;
    each part is (study directory name, suffix appended to its method labels).
    Missing studies are skipped."""
    rows, results, order = [], [], []
    for name, suffix in parts:
        study = Path(root) / name
        if not (study / "summary.csv").exists():
            continue
        for r in read_csv(study / "summary.csv"):
            r["method"] += suffix
            rows.append(r)
            if r["method"] not in order:
                order.append(r["method"])
        for r in read_csv(study / "results.csv"):
            r["method"] += suffix
            results.append(r)
    return rows, results, order


def final_values(results, method: str, metric: str, tail: float = 0.0) -> dict[str, float]:
    """{seed: a method's last test value of ``metric``}; with ``tail`` > 0, each seed's value
    is the mean over its evaluations in the last ``tail`` fraction of its training time (the
    SIP paper averages the last 10 %)."""
    by_seed: dict[str, list[tuple[float, float]]] = {}
    for r in results:
        if r["method"] == method and r["split"] == "test" and r["metric"] == metric:
            by_seed.setdefault(str(r["seed"]), []).append((float(r["wall_time"]), float(r["value"])))
    values = {}
    for seed, points in by_seed.items():
        points.sort()
        end = points[-1][0]
        values[seed] = float(np.mean([v for t, v in points if t >= (1 - tail) * end]) if tail > 0 else points[-1][1])
    return values


def final_metric(results, method: str, metric: str, tail: float = 0.0) -> tuple[float, float]:
    """Mean ± std over the finite per-seed values of :func:`final_values` (for seeds that all
    finished; :func:`study_section` counts diverged seeds as failures)."""
    return mean_std(list(final_values(results, method, metric, tail).values()))


def markdown(lines: list[list[str]]) -> str:
    """A Markdown table from rows of cells (the first row is the header)."""
    out = ["| " + " | ".join(lines[0]) + " |", "|" + "---|" * len(lines[0])]
    out += ["| " + " | ".join(line) + " |" for line in lines[1:]]
    return "\n".join(out)


def study_section(root: str | Path, title: str, parts, metrics: Sequence[str], figures: str | Path, name: str) -> str:
    """A reproduction report's Markdown section for one problem: the table (final test loss
    and the extra ``metrics[1:]``, median [95 % interval] over seeds, a diverged seed counting
    as +∞) and one figure per metric, drawn into ``figures/<name>[_<metric>].png``. ``parts``
    as in :func:`load_studies`."""
    from ..plots import draw, loss_vs_time

    rows, results, order = load_studies(root, parts)
    if not rows:
        return f"## {title}: no results under {root} yet\n"
    table = aggregate(rows, order)
    lines = format_table(table, "adam" if "adam" in order else None)
    failed = diverged_seeds(rows)
    for metric in metrics[1:]:
        lines[0].append(f"final test {metric}: median [95% CI]")
        for line in lines[1:]:
            values = final_values(results, line[0], metric)
            values.update(dict.fromkeys(failed.get(line[0], ()), math.inf))
            line.append(median_cell(summarize(list(values.values()))))
    seeds = len({r["seed"] for r in rows})
    out = [f"## {title} ({seeds} seeds)\n\n{markdown(lines)}\n"]
    notes = {t["method"]: f"{t['diverged']} of {t['runs']} diverged" for t in table if t["diverged"]}
    for metric in metrics:
        figure = name if metric == "loss" else f"{name}_{metric}"
        path = draw(
            loss_vs_time, results, Path(figures) / f"{figure}.png", order=order, metric=metric, notes=notes,
            diverged=failed, title=f"{title}: test {metric}, {seeds} seeds (thin: each seed; line: median over seeds)",
        )  # fmt: skip
        if path is not None:  # else a FigureWarning said why
            out.append(f"![{title}](figures/{path.name})\n")
    return "\n".join(out)

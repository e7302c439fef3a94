"""Sweeps: a grid of settings, one study per cell, and the grid's table and panel figure.

``--set poles=1,2,3,4 --set clip=value,norm,none`` expands to the 12 cells of the grid;
each cell is an ordinary study in ``OUT/<cell>/`` (e.g. ``OUT/poles2_clipnorm/``), so a
grid resumes cell by cell and run by run, and ``OUT/grid.json`` records the grid.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from ...engine import rundir
from ...engine.progress import AbstractProgressMeter
from ...errors import ConfigError
from ..config import Budget, choose
from ..papers import protocol
from ..seeds import aggregate, as_float, median_cell, runs_cell
from .reports import report
from .running import compare, plan
from .tables import collect, diverged_seeds, method_order, read_csv, write_csv


def split_grid(settings: dict[str, Any]) -> tuple[dict[str, Any], dict[str, list[str]]]:
    """(fixed settings, swept settings): a value with commas, ``a,b,c``, is swept."""
    fixed, grid = {}, {}
    for key, value in settings.items():
        if isinstance(value, str) and "," in value:
            values = [v.strip() for v in value.split(",")]
            if not all(values) or len(values) < 2:  # "lr=1e-3," is a typo, not a one-cell sweep
                raise ConfigError(f"setting {key!r}: {value!r} has an empty value; a sweep lists two or more "
                                  "values separated by commas, e.g. lr=1e-3,1e-2")  # fmt: skip
            if len(values) != len(set(values)):
                raise ConfigError(f"setting {key!r} lists a value twice: {value!r}")
            grid[key] = values
        else:
            fixed[key] = value
    return fixed, grid


def grid_cells(grid: dict[str, list[str]]) -> list[dict[str, str]]:
    """Every combination of the swept values, the first setting varying slowest."""
    import itertools

    names = list(grid)
    return [dict(zip(names, values)) for values in itertools.product(*(grid[n] for n in names))]


def cell_name(cell: dict[str, str]) -> str:
    """A cell's directory name: ``{"poles": "2", "clip": "norm"}`` → ``poles2_clipnorm``."""
    return "_".join(f"{k.replace('.', '-')}{v}" for k, v in cell.items())


def compare_grid(
    problem: str,
    methods: Sequence[str] | None,
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any],
    progress: Callable[[], AbstractProgressMeter] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    calibrate: bool = True,
) -> None:
    """Every cell of a settings grid as its own study under ``out`` (validated first); each
    cell calibrates its own seconds budget (its settings may change the step's cost)."""
    fixed, grid = split_grid(settings)
    cells = grid_cells(grid)
    for cell in cells:  # every name and value is checked before anything runs
        plan(problem, methods, seeds, budget, {**fixed, **cell})
    out = Path(out)
    with rundir.one_writer(out, "sweep"):  # one writer per sweep directory, for the whole sweep
        rundir.atomic_write(out / "grid.json", json.dumps({
            "problem": problem, "methods": list(methods or protocol(problem).methods), "seeds": list(seeds),
            "budget": budget.to_dict(), "settings": fixed, "grid": grid,
        }, indent=2) + "\n")  # fmt: skip
        for i, cell in enumerate(cells, 1):
            echo(f"cell {i}/{len(cells)}: {', '.join(f'{k}={v}' for k, v in cell.items())}")
            compare(problem, methods, seeds, budget, out / cell_name(cell), settings={**fixed, **cell},
                    progress=progress, echo=echo, devices=devices, calibrate=calibrate)  # fmt: skip
            report(out / cell_name(cell))


class GridReport(NamedTuple):
    """A grid's table (one row per cell × method), its printable lines and the panel figure."""

    rows: list[dict[str, Any]]
    lines: list[list[str]]
    figure: Path | None


def grid_report(
    out: str | Path,
    *,
    panel: str | None = None,
    metric: str = "loss",
    split: str = "test",
    smooth: int = 1,
    figure: str | Path | None = None,
    methods: Sequence[str] | None = None,
) -> GridReport:
    """Table and panel figure of a grid from its cells' files: one panel per value of
    ``panel`` (default: the first swept setting), one colour per method and one line style
    per value of the other swept settings; x = epochs, y = ``split`` ``metric`` (log),
    optionally a ``smooth``-epoch moving average (the StableBPTT plots use 30). The figure
    goes to ``figure`` (default ``OUT/grid[_metric].png``); ``methods`` fixes the colour
    order (default: the grid's methods), so several reports can share colours."""
    from ..plots import draw, grid_panels

    out = Path(out)
    if not (out / "grid.json").exists():
        raise ConfigError(f"{out} is not a grid directory: grid.json is missing")
    info = rundir.read_json(out / "grid.json", rundir.NOT_A_STUDY)
    grid = info["grid"]
    panel = panel or next(iter(grid))
    choose("panel setting", panel, grid)
    head = ["cell", "method", "runs", "final test loss: median [95% CI] over seeds", "best test loss", "ms/step"]
    rows, curves, lines = [], [], [head]
    for cell in grid_cells(grid):
        study = out / cell_name(cell)
        if (study / "runs").exists():
            collect(study)  # the cell's files may predate runs finished since
        if not (study / "summary.csv").exists():
            continue
        summary = read_csv(study / "summary.csv")
        per_epoch = {(r["method"], r["seed"]): as_float(r["epochs"]) / max(as_float(r["steps"]), 1.0) for r in summary}
        results = [r for r in read_csv(study / "results.csv") if r["split"] == split and r["metric"] == metric]
        for r in results:
            r["epoch"] = float(r["step"]) * per_epoch.get((r["method"], r["seed"]), math.nan)
        failed = diverged_seeds(summary)
        for r in results:
            r["diverged"] = str(r["seed"]) in failed.get(r["method"], ())
        for t in aggregate(summary, method_order(summary, info)):
            final, label = t["final"], ", ".join(f"{k}={v}" for k, v in cell.items())
            rows.append({**cell, "method": t["method"], "runs": t["runs"], "diverged": t["diverged"],
                         "final_test_loss": final["mean"], "final_test_loss_std": final["std"],
                         "best_test_loss": t["best"]["median"], "ms_per_step": t["ms_per_step"],
                         "final_test_loss_median": final["median"], "final_test_loss_low": final["low"],
                         "final_test_loss_high": final["high"]})  # fmt: skip
            lines.append([label, t["method"], runs_cell(t["runs"], t["diverged"]), median_cell(final),
                          f"{t['best']['median']:.3e}", f"{t['ms_per_step']:.2f}"])  # fmt: skip
        curves.append((cell, results))
    write_csv(out / "grid_summary.csv", [*grid, "method", "runs", "diverged", "final_test_loss", "final_test_loss_std",
                                         "best_test_loss", "ms_per_step", "final_test_loss_median",
                                         "final_test_loss_low", "final_test_loss_high"], rows)  # fmt: skip
    suffix = "" if metric == "loss" else f"_{metric}"
    smoothing = f", {smooth}-epoch moving average" if smooth > 1 else ""
    figure = draw(  # after grid_summary.csv: a failing figure is a warning
        grid_panels, curves, figure or out / f"grid{suffix}.png", panel=panel, methods=methods or info["methods"], metric=f"{split} {metric}",
        smooth=smooth,
        title=f"{info['problem']}: {split} {metric} per epoch ({len(info['seeds'])} seeds, line: median over seeds{smoothing})",
    )  # fmt: skip
    return GridReport(rows, lines, figure)

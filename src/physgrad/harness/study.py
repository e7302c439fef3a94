"""Method × seed comparisons on equal budgets, and their result tables.

A study directory holds ``study.json`` (what was asked), ``runs/<method>-seed<k>-<hash>/``
(one run directory each; the hash is of the run's canonical configuration, so a changed
setting makes a new run), ``results.csv`` (every run's metrics in long format with problem,
method and seed columns), ``summary.csv`` (one row per run), ``loss_vs_time.png`` and,
where runs raised and the study went on, ``failures.json``.
Running the same study again skips finished (or diverged) runs and resumes interrupted
ones from their checkpoints.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .. import rundir
from ..engine.recording import gzip_bytes, kept_path, open_kept, packed_path
from ..errors import ConfigError
from ..progress import AbstractProgressMeter
from .config import Budget, RunConfig, choose, make_config, method_slug, parse_method, phase_methods, valid_settings
from .failures import FailureLog, recordable
from .papers import protocol
from .registry import PROBLEMS
from .seeds import aggregate, as_float, format_table, mean_std, median_cell, paired_ratio, runs_cell, summarize
from .train import is_complete, read_metrics, read_summary, train

SUMMARY_COLUMNS = (
    "problem", "method", "seed", "status", "steps", "epochs", "train_seconds", "time_per_step",
    "final_train_loss", "final_test_loss", "best_test_loss", "diverged_step", "last_finite_loss",
    "compile_seconds", "run_dir", "calibrated_seconds", "calibrated_ms_per_step", "wall_capped",
)  # fmt: skip
RESULT_COLUMNS = ("problem", "method", "seed", "step", "wall_time", "split", "metric", "value", "calibrated_time")


def settings_for(problem: str, method: str, methods: Sequence[str], settings: dict[str, Any]) -> dict[str, Any]:
    """The subset of a study's ``--set`` values that applies to one method (or sequence).

    ``name=value`` applies to every method that has the setting (it must exist for at least
    one); ``m.name=value`` applies to method ``m``, also where ``m`` is a stage of a
    sequence such as ``adam:2000,hig``.
    """
    from .config import split_scope  # here: the module-level import line is full

    names = set(phase_methods(method))
    everywhere = sorted(set().union(*(phase_methods(m) for m in methods)))
    out = {}
    for key, value in settings.items():
        target, name = split_scope(key)
        if target:
            choose("method in a scoped setting", target, everywhere)
            if target in names:
                out[key] = value  # validated by make_config
        elif name in valid_settings(problem, method):
            out[name] = value
        elif not any(name in valid_settings(problem, m) for m in methods):
            valid = sorted(set().union(*(valid_settings(problem, m) for m in methods)))
            raise ConfigError(f"unknown setting {name!r} for {problem}; valid choices: {', '.join(valid)}")
    return out


def plan(
    problem: str,
    methods: Sequence[str] | None,
    seeds: Sequence[int],
    budget: Budget,
    settings: dict[str, Any] | None = None,
) -> list[RunConfig]:
    """The run configurations of a study, validated before anything runs (``methods`` None: its defaults)."""
    choose("problem", problem, PROBLEMS)
    methods = list(protocol(problem).methods if methods is None else methods)
    for m in methods:
        parse_method(m)
    settings = settings or {}
    return [
        make_config(problem, m, budget=budget, seed=s, settings=settings_for(problem, m, methods, settings))
        for m in methods
        for s in seeds
    ]


def run_name(config: RunConfig) -> str:
    """A readable, deterministic run directory name: method, seed and a config hash
    (a sequence ``adam:2000,hig`` reads ``adam2000+hig``)."""
    return f"{method_slug(config.method)}-seed{config.seed}-{config.digest()}"


def compare(
    problem: str,
    methods: Sequence[str] | None,
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    progress: Callable[[], AbstractProgressMeter] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    record_failures: bool = False,
    calibrate: bool = True,
    calibration_options: dict[str, Any] | None = None,
    executor=None,
) -> list[dict[str, Any]]:
    """Train every method × seed on the same budget into ``out``; return the summary rows.
    ``devices``: each run's batch is split over that many devices (``train``). One study
    writes to ``out`` at a time (a second is refused in one line naming the first).
    ``record_failures``: a run that raises is recorded and the study goes on (the bench's
    choice: one crashing method must not cost the others' runs; :mod:`physgrad.harness.failures`);
    without it the first error stops the study, as bad input and KeyboardInterrupt always do.

    A seconds budget is calibrated (``calibrate``, the default; :mod:`physgrad.harness.calibration`):
    each method's compiled step is timed first (or the study's recorded calibration read
    back), and its runs train for ``seconds / calibrated seconds per step`` steps, their
    ``eval_seconds`` becoming the same cadence in steps. ``calibrate=False`` keeps the
    wall-clock budget (the run stops when its training wall-clock reaches the seconds).
    ``calibration_options``: :func:`~physgrad.harness.calibration.calibrate`'s ``repeats``,
    ``max_seconds``, ``clock`` or ``programs``. ``executor``: where the runs go, all at once
    (:mod:`physgrad.harness.workers`: Dask workers; None: one after the other here)."""
    out = Path(out)
    configs = plan(problem, methods, seeds, budget, settings)
    with rundir.one_writer(out, "study"):  # one writer per study directory, for the whole study
        calibrated = budget.kind == "seconds" and calibrate
        if calibrated:
            calibration = _calibration(out, configs, echo=echo, devices=devices, record_failures=record_failures,
                                       **(calibration_options or {}))  # fmt: skip
            configs = [calibrated_config(c, calibration, float(budget.amount)) for c in configs]
        names = [run_name(c) for c in configs]
        rundir.atomic_write(out / "study.json", json.dumps({
            "problem": problem, "methods": list(dict.fromkeys(c.method for c in configs)), "seeds": list(seeds),
            "budget": budget.to_dict(), "settings": settings or {}, "runs": names, "calibrated": calibrated,
            "run_budgets": {c.method: c.budget.to_dict() for c in configs},
        }, indent=2) + "\n")  # fmt: skip
        log = FailureLog(out, names, write=record_failures)
        pending = []  # --- executor injection (harness/workers.py): the runs left, handed over at once
        for i, (config, name) in enumerate(zip(configs, names), 1):
            run_dir = out / "runs" / name
            prefix = f"[{i}/{len(configs)}] {config.method} seed {config.seed}"
            if is_complete(run_dir) and not cap_raised(read_summary(run_dir) or {}, config.wall_cap):
                echo(f"{prefix}: done already ({(read_summary(run_dir) or {}).get('status')}), skipped")
                continue
            if executor is not None:
                pending.append((prefix, config, run_dir))
                continue
            try:
                summary = train(config, run_dir, resume=True, progress=progress and progress(), devices=devices)
            except Exception as e:  # KeyboardInterrupt is no Exception: it always stops the study
                if not (record_failures and recordable(e)):
                    raise
                echo(f"{prefix}: failed, recorded ({log.record(name, config.method, config.seed, e)})")
                continue
            log.clear(name)
            echo(f"{prefix}: {describe_run(summary)}")
        if pending:
            from .workers import run_pending

            run_pending(executor, pending, log, record_failures=record_failures, echo=echo, devices=devices)
        return collect(out)  # --- end of the executor injection


def calibrate_study(
    problem: str,
    methods: Sequence[str] | None,
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
) -> dict[str, list[Any]]:
    """The calibration phase of :func:`compare` alone: each method's step timed into
    ``out/calibration.json`` (or the recorded one read back), nothing trained. ``compare``
    on the same directory then reuses it, so a study calibrated on a quiet machine trains
    with the same step counts under any load. Returns each method's stage costs."""
    out = Path(out)
    configs = plan(problem, methods, [0], budget, settings)
    out.mkdir(parents=True, exist_ok=True)
    with rundir.one_writer(out, "study"):
        calibration = _calibration(out, configs, echo=echo, devices=devices)
    return {c.method: calibration.stages(c.method) for c in configs if calibration.has(c.method)}


def _calibration(out: Path, configs: Sequence[RunConfig], **options: Any):
    """The study's calibration (:func:`physgrad.harness.calibration.study_calibration`) of
    each method's seed-0 run: the seeds share its step program."""
    from .calibration import study_calibration

    firsts: dict[str, RunConfig] = {}
    for c in configs:
        firsts.setdefault(c.method, dataclasses.replace(c, seed=0))
    return study_calibration(out, firsts, **options)


def cap_raised(summary: dict[str, Any], wall_cap: float) -> bool:
    """Whether a run that a wall-clock cap stopped may train on: the cap is now higher, or gone."""
    return bool(summary.get("wall_capped")) and (wall_cap <= 0 or wall_cap > summary.get("train_seconds", 0.0))


def calibrated_config(config: RunConfig, calibration, seconds: float) -> RunConfig:
    """A run of a calibrated study: ``seconds`` of calibrated time as a step budget, and its
    ``eval_seconds`` (training seconds between evaluations) as ``eval_every`` steps at its
    last stage's calibrated cost, so that evaluations fall at the same calibrated times
    whatever the load. A method without a calibration (its step could not be built) keeps
    the wall-clock budget: its run meets the same error and is recorded."""
    if not calibration.has(config.method):
        return config
    changes: dict[str, Any] = {"budget": Budget(steps=calibration.steps(config.method, seconds))}
    if config.eval_seconds > 0:
        every = max(1, round(config.eval_seconds / calibration.seconds_per_step(config.method)))
        changes.update(eval_every=every, eval_seconds=0.0)
    return dataclasses.replace(config, **changes)


def describe_run(summary: dict[str, Any]) -> str:
    """One line about a finished run."""
    if summary["status"] == "diverged":
        return f"diverged at step {summary['diverged_step']} (last finite loss {summary['last_finite_loss']})"
    failures = (summary.get("step_stat_totals") or {}).get("inverse_failures", 0)
    return (
        f"test loss {summary['final_test_loss']:.3e} after {summary['steps']} steps "
        f"({1e3 * summary['time_per_step']:.2f} ms/step)"
        + (f"; {failures:.0f} local inverse solves failed (their samples got no update)" if failures else "")
    )


def collect(out: str | Path) -> list[dict[str, Any]]:
    """Gather the runs of a study into ``results.csv`` and ``summary.csv`` (only the runs
    that ``study.json`` plans, when it lists them: a directory reused with another budget or
    setting keeps the old runs' directories, which must not mix into the tables)."""
    from .calibration import read as read_calibration

    out = Path(out)
    rows, results = [], []
    study = rundir.read_json(out / "study.json", rundir.NOT_A_STUDY, empty={})
    planned = set(study.get("runs", [])) or None  # a reused directory keeps other plans' runs
    calibration = read_calibration(out)
    for run_dir in sorted((out / "runs").glob("*")):
        if planned is not None and run_dir.name not in planned:
            continue
        summary, config_path = read_summary(run_dir), run_dir / "config.json"
        if summary is None or summary.get("status") not in ("finished", "diverged") or not config_path.exists():
            continue
        config = rundir.read_json(config_path, rundir.RUN_DAMAGED)
        try:
            ident = {"problem": config["problem"], "method": config["method"], "seed": config["seed"]}
        except KeyError as e:
            raise ConfigError(f"{config_path} lacks {e}; {rundir.RUN_DAMAGED}") from None
        clock = (lambda step, m=config["method"]: calibration.time_at(m, step)) if calibration and calibration.has(
            config["method"]) else None  # fmt: skip
        row = {**{k: summary.get(k) for k in SUMMARY_COLUMNS}, **ident, "run_dir": str(run_dir.relative_to(out))}
        if clock is not None and isinstance(summary.get("steps"), int):
            row["calibrated_seconds"] = clock(summary["steps"])
            row["calibrated_ms_per_step"] = 1e3 * calibration.seconds_per_step(config["method"])  # type: ignore[union-attr]
        rows.append(row)
        try:
            metrics = read_metrics(run_dir / "metrics.csv")
        except (OSError, ValueError, KeyError, TypeError, EOFError, csv.Error) as e:
            raise ConfigError(f"{run_dir / 'metrics.csv'} cannot be read ({type(e).__name__}); "
                              f"{rundir.RUN_DAMAGED}") from None  # fmt: skip
        results += [{**ident, **r, **({"calibrated_time": clock(r["step"])} if clock else {})} for r in metrics]
    write_csv(out / "summary.csv", SUMMARY_COLUMNS, rows)
    write_csv(out / "results.csv", RESULT_COLUMNS, results)
    return rows


def write_csv(path: Path, columns: Sequence[str], rows: list[dict[str, Any]]):
    """A table written all at once (:func:`physgrad.rundir.atomic_write`; never half). A
    table kept gzipped (``path.gz`` exists: a committed study, docs/reproductions/
    keep_studies.py --gzip) is rewritten gzipped and any plain copy beside it removed, so
    re-collecting a kept study leaves one copy, never a stale one."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(columns), extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    packed = packed_path(path)
    if packed.exists():
        rundir.atomic_write(packed, gzip_bytes(text.getvalue().encode()))
        Path(path).unlink(missing_ok=True)
    else:
        rundir.atomic_write(path, text.getvalue())


def read_csv(path: str | Path) -> list[dict[str, Any]]:  # str values; callers add numbers
    """The rows of a CSV file, or of its gzipped copy where only that exists (:func:`kept_path`)."""
    with open_kept(path) as f:
        return list(csv.DictReader(f))


def method_order(rows: list[dict[str, Any]], study: dict[str, Any] | None = None) -> list[str]:
    """Methods in the study's order (or first appearance)."""
    listed = list((study or {}).get("methods", []))
    return listed + [m for m in dict.fromkeys(r["method"] for r in rows) if m not in listed]


class Report(NamedTuple):
    """A study's aggregated table (per method, :func:`physgrad.harness.seeds.aggregate`), its
    printable lines and the figure's path (None: the figure could not be drawn, a
    :class:`~physgrad.harness.plots.FigureWarning` says why)."""

    table: list[dict[str, Any]]
    lines: list[list[str]]
    figure: Path | None

    def final_test_loss(self, method: str) -> float:
        """Median final test loss of one method over its seeds, a diverged seed counting as
        +∞ (NaN if the method has no run)."""
        return next((t["final"]["median"] for t in self.table if t["method"] == method), math.nan)

    def ratio(self, method: str, reference: str) -> dict[str, Any]:
        """``method``'s final test loss over ``reference``'s, paired by seed: the median of
        the per-seed ratios with its interval (:func:`physgrad.harness.seeds.summarize`)."""
        rows = {t["method"]: t for t in self.table}
        return paired_ratio(rows[method], rows[reference])


def diverged_seeds(rows: list[dict[str, Any]]) -> dict[str, set[str]]:
    """{method: the seeds (as text) whose runs diverged}, for the figures' marks."""
    out: dict[str, set[str]] = {}
    for r in rows:
        if r["status"] == "diverged":
            out.setdefault(r["method"], set()).add(str(r["seed"]))
    return out


def report(out: str | Path) -> Report:
    """Re-draw a study's table and figure from its files alone (``summary.csv``, ``results.csv``,
    the runs' ``test_cases.json`` for the test-case spread)."""
    from .plots import draw, loss_vs_time
    from .stats import case_spread

    out = Path(out)
    for name in ("summary.csv", "results.csv"):
        if not kept_path(out / name).exists():
            raise ConfigError(f"{out} is not a study directory: {name} is missing")
    study = rundir.read_json(out / "study.json", rundir.NOT_A_STUDY, empty={})
    rows = read_csv(out / "summary.csv")
    order = method_order(rows, study)
    table = aggregate(rows, order, spread=case_spread(out, metric="loss"))
    reference = "adam" if "adam" in order else None
    notes = {t["method"]: f"{t['diverged']} of {t['runs']} diverged" for t in table if t["diverged"]}
    figure = draw(  # the table does not depend on it: a failing figure is a warning
        loss_vs_time, read_csv(out / "results.csv"), out / "loss_vs_time.png", order=order, title=_title(study, rows),
        notes=notes, diverged=diverged_seeds(rows),
    )  # fmt: skip
    return Report(table, format_table(table, reference), figure)


def _title(study: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    problem = study.get("problem") or (rows[0]["problem"] if rows else "")
    budget = ", ".join(f"{v:g} {k}" for k, v in study.get("budget", {}).items())
    seeds = len(study.get("seeds", [])) or len({r["seed"] for r in rows})
    return f"{problem}: test loss vs training time ({budget}, {seeds} seed{'s' if seeds != 1 else ''})"


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
    from .plots import draw, loss_vs_time

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


# --- sweeps: a grid of settings, one study per cell ---------------------------------------
#
# ``--set poles=1,2,3,4 --set clip=value,norm,none`` expands to the 12 cells of the grid;
# each cell is an ordinary study in ``OUT/<cell>/`` (e.g. ``OUT/poles2_clipnorm/``), so a
# grid resumes cell by cell and run by run, and ``OUT/grid.json`` records the grid.


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
    from .plots import draw, grid_panels

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

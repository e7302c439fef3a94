"""The study commands' bodies on the console: ``physgrad compare`` (a study, a sweep, or its
calibration alone), ``physgrad calibrate``, ``physgrad report`` on a study or a sweep, and
the demo's verdict; each prints the tables this package's files hold
(:class:`~physgrad.harness.options.StudyOptions` carries the flags)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from ...engine import rundir
from ...engine.types import Seconds
from ..arguments import UsageError
from ..console import files, print_table
from ..options import CalibrateOptions, ReportOptions, StudyOptions


def _meter(options: StudyOptions, console):
    """A progress bar per run in a terminal (none with --quiet or in a pipe)."""
    from ...engine.progress import RichProgressMeter

    return None if options.quiet or not console.is_terminal else RichProgressMeter


def run_compare(console, options: StudyOptions, executor=None):
    """One study: validated, trained (:func:`~physgrad.harness.study.compare`), then its table,
    paired tests and time-to-target table printed; returns its :class:`~physgrad.harness.study.Report`."""
    from ..seeds import table_note
    from . import compare, plan, report

    problem, methods, seeds, budget, settings, out = (options.problem, options.methods, options.seeds, options.budget,
                                                      options.settings, options.out)  # fmt: skip
    plan(problem, methods, seeds, budget, settings)  # validate every name before anything runs
    calibrated = options.calibrate and isinstance(budget, Seconds)
    console.print(
        f"comparing on {problem}: budget {budget}{' (calibrated)' if calibrated else ''} per run, seeds {list(seeds)}, "
        f"settings {settings or 'paper defaults'}"
    )
    compare(problem, methods, seeds, budget, out, settings=settings, progress=_meter(options, console),
            echo=console.print, devices=options.devices, calibrate=options.calibrate, executor=executor)  # fmt: skip
    result = report(out)
    print_table(console, result.lines, title=f"{problem}: {budget} per run", caption=table_note(result.table))
    print_paired_tests(console, out)
    print_targets(console, out)
    extra = [Path(out) / name for name in ("calibration.json", "time_to_target.csv") if (Path(out) / name).exists()]
    console.print(f"wrote {files(Path(out) / 'results.csv', Path(out) / 'summary.csv', *extra, result.figure)}")
    return result


def run_grid(console, options: StudyOptions) -> None:
    """A sweep: ``--set a=1,2 --set b=x,y`` runs every cell of the grid as its own study."""
    from . import compare_grid, grid_cells, grid_report, split_grid

    problem, budget, out = options.problem, options.budget, options.out
    fixed, grid = split_grid(options.settings)
    console.print(
        f"sweeping {problem} over {' x '.join(f'{k} in {{{chr(44).join(v)}}}' for k, v in grid.items())} "
        f"({len(grid_cells(grid))} cells): budget {budget} per run, seeds {list(options.seeds)}, fixed settings {fixed or 'paper defaults'}"
    )
    compare_grid(problem, options.methods, options.seeds, budget, out, settings=options.settings,
                 progress=_meter(options, console), echo=console.print, devices=options.devices,
                 calibrate=options.calibrate)  # fmt: skip
    result = grid_report(out)
    print_table(console, result.lines, title=f"{problem}: {budget} per run")
    print_paired_tests(console, out)
    console.print(f"wrote {files(Path(out) / 'grid_summary.csv', result.figure)}")


def calibrate_only(console, options: StudyOptions) -> int:
    """``compare --calibrate-only``: each method's step timed into ``out/calibration.json``
    (:func:`~physgrad.harness.study.calibrate_study`); nothing trains."""
    from ..calibration import steps_for as calibration_steps
    from . import calibrate_study, split_grid

    budget = options.budget
    if not isinstance(budget, Seconds) or not options.calibrate:
        raise UsageError("--calibrate-only needs a calibrated --seconds budget")
    if split_grid(options.settings)[1]:
        raise UsageError("--calibrate-only takes one study, not a sweep (a comma-separated --set value)")
    calibration = calibrate_study(options.problem, options.methods, budget, options.out, settings=options.settings,
                                  echo=console.print, devices=options.devices)  # fmt: skip
    for method, stages in calibration.items():
        costs = ", ".join(f"{s.method} {1e3 * s.seconds:.4g} ms/step" for s in stages)
        console.print(f"{method}: {costs} -> {calibration_steps(float(budget.amount), stages)} steps for {budget}")
    console.print(f"wrote {Path(options.out) / 'calibration.json'}; nothing was trained")
    return 0


def print_targets(console, out) -> None:
    """The study's time-to-target table (:mod:`physgrad.harness.targets`), where its problem declares a target."""
    from ..targets import study_times, table_lines

    target, runs, table = study_times(out)
    if target is None or not table:
        return
    axis = runs[0]["axis"] if runs else "wall-clock"
    print_table(console, table_lines(target, table, axis), title=f"time to the target test loss {target.loss:g}",
                caption=f"target: {target.origin} ({target.why}). First evaluation at or below the target, no "
                        "interpolation; >budget: never reached (censored); a diverged seed never reaches it; "
                        "median over seeds, those seeds included")  # fmt: skip


def print_paired_tests(console, out) -> None:
    """Paired comparisons between the methods of a study or of each cell of a sweep, by seed
    (:func:`physgrad.harness.stats.paired_tests`)."""
    from ..stats import MIN_SEEDS_P, format_tests, paired_tests

    out = Path(out)
    cells = (
        [(c.name, c) for c in sorted(out.iterdir()) if (c / "study.json").exists()]
        if (out / "grid.json").exists()
        else [("", out)]
    )
    lines: list[list[str]] = []
    for name, directory in cells:
        study = rundir.read_json(directory / "study.json", rundir.NOT_A_STUDY, empty={})
        rows = paired_tests(directory, order=study.get("methods"))
        table = format_tests(rows, cell=name or "")
        lines += table if not lines else table[1:]
    if len(lines) > 1:
        print_table(console, lines, title="methods paired by seed",
                    caption=f"a diverged seed is the worse value; ratio: median of the per-seed ratios; "
                            f"two-sided Wilcoxon signed-rank test over seeds, from {MIN_SEEDS_P} seeds that differ "
                            "(below, its smallest p-value 2/2^n cannot reach 0.05)")  # fmt: skip


def print_report(console, options: ReportOptions) -> int:
    """``physgrad report`` on a sweep (``grid.json``) or a study: its tables redrawn from its files."""
    from ..seeds import table_note
    from . import grid_report, report

    if (Path(options.dir) / "grid.json").exists():
        result = grid_report(options.dir, panel=options.panel, metric=options.metric, split=options.split,
                             smooth=options.smooth)  # fmt: skip
        print_table(console, result.lines, title=str(options.dir))
        print_paired_tests(console, options.dir)
        console.print(f"wrote {files(Path(options.dir) / 'grid_summary.csv', result.figure)}")
        return 0
    result = report(options.dir)
    print_table(console, result.lines, title=str(options.dir), caption=table_note(result.table))
    print_paired_tests(console, options.dir)
    print_targets(console, options.dir)
    if result.figure:
        console.print(f"wrote {result.figure}")
    return 0


def calibrate_command(console, options: CalibrateOptions) -> int:
    """``physgrad calibrate``: the calibration phase of a study alone, as a table (and a file)."""
    from ...engine.types import Steps
    from ..calibration import CSV_COLUMNS, EXTRA_COLUMNS, Calibration, calibrate, csv_rows, write_csv
    from . import plan, read_csv

    configs = plan(options.problem, options.methods, [0], Steps(1), options.settings)
    timing: dict[str, Any] = {k: v for k, v in (("repeats", options.repeats), ("max_seconds", options.max_seconds))
                              if v is not None}  # fmt: skip
    record = calibrate({c.method: c for c in configs}, devices=options.devices, echo=console.print, **timing)
    rows = csv_rows(Calibration(record), command=options.command)
    lines = [["method", "stage", "route", "batch", "ms/step (median)", "quartiles", "min-max", "rounds", "compile s"]]
    for r in rows:
        lines.append([r["spec"], str(r["stage"]), r["route"], str(r["batch"]), r["ms_per_step"],
                      f"{r['ms_q25']}-{r['ms_q75']}", f"{r['ms_min']}-{r['ms_max']}", str(r["rounds"]),
                      r["compile_seconds"]])  # fmt: skip
    print_table(
        console, lines, title=f"{options.problem}: calibrated step times ({rows[0]['machine'] if rows else ''})"
    )
    out = options.out
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        if out.suffix == ".json":
            rundir.atomic_write(
                out, json.dumps(record, indent=2, default=str) + "\n"
            )  # the old record stays on a failed write
        else:
            if options.append and out.exists():
                rows = [*read_csv(out), *rows]
            write_csv(out, rows)
        console.print(f"wrote {out} ({', '.join(CSV_COLUMNS)}, then {', '.join(EXTRA_COLUMNS)})"
                      if out.suffix == ".csv" else f"wrote {out}")  # fmt: skip
    return 0


def print_demo_verdict(console, result) -> None:
    """The demo's last line: HIG's final test loss against Adam's, paired by seed."""
    from ..seeds import interval

    ratio = result.ratio("adam", "hig")  # Adam's final test loss over HIG's, per seed
    r, seeds = ratio["median"], f"median over {ratio['n']} seed{'s' if ratio['n'] != 1 else ''} of the per-seed ratio"
    spread = f"95% CI {interval(ratio, '.3g')}"
    if ratio["n"] == 0 or math.isnan(r):
        console.print("No HIG/Adam ratio: the two have no seed in common (see the table).")
    elif math.isinf(r):
        console.print(f"Adam diverged on at least half the seeds where HIG did not ({seeds}: ∞; see the table).")
    elif r == 0:
        console.print(f"HIG diverged on at least half the seeds where Adam did not ({seeds}: 0; see the table).")
    elif r >= 1:
        console.print(f"HIG's final test loss is {r:.1f}x below Adam's at equal calibrated time ({seeds}; {spread}).",
                      markup=False)  # fmt: skip
    else:
        console.print(f"HIG's final test loss is {1 / r:.1f}x above Adam's at equal calibrated time ({seeds}; {spread}).",
                      markup=False)  # fmt: skip

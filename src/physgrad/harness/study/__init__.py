"""Method × seed comparisons on equal budgets, and their result tables.

A study directory holds ``study.json`` (what was asked), ``runs/<method>-seed<k>-<hash>/``
(one run directory each; the hash is of the run's canonical configuration, so a changed
setting makes a new run), ``results.csv`` (every run's metrics in long format with problem,
method and seed columns), ``summary.csv`` (one row per run), ``loss_vs_time.png`` and,
where runs raised and the study went on, ``failures.json``.
Running the same study again skips finished (or diverged) runs and resumes interrupted
ones from their checkpoints.

One module per concern; every name is published here:

- :mod:`~physgrad.harness.study.running`: the plan and the runs (:func:`compare`);
- :mod:`~physgrad.harness.study.tables`: ``results.csv`` and ``summary.csv`` (:func:`collect`)
  and the CSV reading and writing;
- :mod:`~physgrad.harness.study.reports`: the table and figure re-drawn from the files (:func:`report`);
- :mod:`~physgrad.harness.study.grid`: sweeps, one study per cell of a settings grid;
- :mod:`~physgrad.harness.study.sections`: the reproduction reports' Markdown sections.
"""

from ...engine.recording import kept_path  # the reports read kept (gzipped) tables through it
from .grid import GridReport, cell_name, compare_grid, grid_cells, grid_report, split_grid
from .reports import Report, report
from .running import (
    calibrate_study,
    calibrated_config,
    cap_raised,
    compare,
    describe_run,
    plan,
    run_name,
    settings_for,
)
from .sections import final_metric, final_values, load_studies, markdown, study_section
from .tables import RESULT_COLUMNS, SUMMARY_COLUMNS, collect, diverged_seeds, method_order, read_csv, write_csv

__all__ = [
    "RESULT_COLUMNS",
    "SUMMARY_COLUMNS",
    "GridReport",
    "Report",
    "calibrate_study",
    "calibrated_config",
    "cap_raised",
    "cell_name",
    "collect",
    "compare",
    "compare_grid",
    "describe_run",
    "diverged_seeds",
    "final_metric",
    "final_values",
    "grid_cells",
    "grid_report",
    "kept_path",
    "load_studies",
    "markdown",
    "method_order",
    "plan",
    "read_csv",
    "report",
    "run_name",
    "settings_for",
    "split_grid",
    "study_section",
    "write_csv",
]

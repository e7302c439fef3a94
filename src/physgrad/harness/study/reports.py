"""A study's report, re-drawn from its files alone: the table aggregated per method over
seeds and the loss-versus-time figure (:func:`report`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, NamedTuple

from ...engine import rundir
from ...engine.recording import kept_path
from ...errors import ConfigError
from ..seeds import aggregate, format_table, paired_ratio
from .tables import diverged_seeds, method_order, read_csv


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


def report(out: str | Path) -> Report:
    """Re-draw a study's table and figure from its files alone (``summary.csv``, ``results.csv``,
    the runs' ``test_cases.json`` for the test-case spread)."""
    from ..plots import draw, loss_vs_time
    from ..stats import case_spread

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

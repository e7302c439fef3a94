"""A bench's report, (re)written from its files alone: every problem's table, the leaderboard,
the heat map and ``bench.md`` (see :mod:`physgrad.harness.bench` for the layout)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

from ...rundir import atomic_write
from .. import plots
from ..config import ConfigError
from ..failures import read_failures
from ..stats import paired_tests
from ..study import collect, markdown, read_csv, write_csv
from ..study import report as study_report
from .applicability import Verdict
from .tables import (
    BOARD_COLUMNS,
    RATIO_CLIP,
    REFERENCE,
    TABLE_COLUMNS,
    add_paired_tests,
    best_method,
    board_lines,
    board_records,
    leaderboard,
    method_rows,
    table_lines,
    table_records,
)


class BenchReport(NamedTuple):
    """The bench's tables (``{problem: method rows}``), leaderboard and written files."""

    tables: dict[str, list[dict[str, Any]]]
    board: list[dict[str, Any]]
    files: dict[str, Path | None]  # the heat map's is None where it could not be drawn (a FigureWarning)

    @property
    def lines(self) -> list[list[str]]:
        """The leaderboard's printable lines."""
        return board_lines(self.board)


def problem_table(out: str | Path, verdicts: Sequence[Verdict]) -> list[dict[str, Any]]:
    """One problem's method rows from its study directory, with the paired tests against
    the best method (written to its ``paired_tests.csv``: metric ``loss``, best first) and
    its loss-vs-time figure redrawn."""
    out = Path(out)
    rows = []
    if (out / "runs").exists():
        collect(out)  # the files may predate runs finished since (or a bench interrupted)
        rows = read_csv(out / "summary.csv")
    table = method_rows(rows, verdicts, read_failures(out))
    tests = []
    if rows:
        study_report(out)  # loss_vs_time.png, as compare draws it
        best = best_method(table)
        others = [t["method"] for t in table if t["method"] != best and t["finished"]]
        if best and others:
            tests = paired_tests(out, metric="loss", order=[best, *others])
    return add_paired_tests(table, tests)


def heatmap(
    tables: dict[str, Sequence[dict[str, Any]]], path: str | Path, *, title: str = "", reference: str = REFERENCE
) -> Path:
    """The bench's method × problem heat map (:func:`physgrad.harness.plots.heatmap`) of the ratios
    to ``reference``, clipped to :data:`~physgrad.harness.bench.tables.RATIO_CLIP` as the leaderboard's."""
    return plots.heatmap(tables, path, title=title, reference=reference, clip=RATIO_CLIP)


def report(out: str | Path) -> BenchReport:
    """(Re)write a bench's tables, leaderboard, heat map and ``bench.md`` from its files
    (each written all at once)."""
    out = Path(out)
    if not (out / "bench.json").exists():
        raise ConfigError(f"{out} is not a bench directory: bench.json is missing")
    info = json.loads((out / "bench.json").read_text())
    tables, files = {}, {}
    for problem in info["problems"]:
        verdicts = [Verdict(**v) for v in info["verdicts"][problem]]
        table = problem_table(out / problem, verdicts)
        tables[problem] = table
        (out / problem).mkdir(exist_ok=True)  # a bench interrupted before this problem: its table says pending
        write_csv(out / problem / "bench_table.csv", TABLE_COLUMNS, table_records(problem, table))
        atomic_write(out / problem / "bench_table.md", markdown(table_lines(table)) + "\n")
    board = leaderboard(tables)
    write_csv(out / "leaderboard.csv", BOARD_COLUMNS, board_records(board))
    atomic_write(out / "leaderboard.md", markdown(board_lines(board)) + "\n")
    write_csv(out / "bench_table.csv", TABLE_COLUMNS, [r for p, t in tables.items() for r in table_records(p, t)])
    files["leaderboard"] = out / "leaderboard.csv"
    files["table"] = out / "bench_table.csv"
    files["markdown"] = out / "bench.md"
    atomic_write(out / "bench.md", bench_markdown(info, tables, board))
    files["heatmap"] = plots.draw(  # last: a failing figure is a warning, the tables are written
        heatmap, tables, out / "heatmap.png", title=f"{_budget_text(info)}: final test loss relative to {REFERENCE}"
    )
    return BenchReport(tables, board, files)


def _budget_text(info: dict[str, Any]) -> str:
    budget = ", ".join(f"{v:g} {k}" for k, v in info["budget"].items())
    seeds = len(info["seeds"])
    return f"{budget} per run, {seeds} seed{'s' if seeds != 1 else ''}"


def bench_markdown(
    info: dict[str, Any], tables: dict[str, Sequence[dict[str, Any]]], board: Sequence[dict[str, Any]]
) -> str:
    """``bench.md``: budgets, machine, settings, leaderboard, heat map and every problem's table."""
    m = info.get("machine", {})
    versions = m.get("versions", {})
    budget = info["budget"]
    kind = next(iter(budget))
    budget_line = {
        "seconds": f"{budget[kind]:g} s of training wall-clock per run (evaluation and compilation excluded), "
                   "the same for every method of a problem",
        "steps": f"{budget[kind]:g} training steps per run",
        "epochs": f"{budget[kind]:g} epochs per run",
    }[kind]  # fmt: skip
    settings = info.get("settings") or {}
    out = [
        "# physgrad bench" + (f" ({info['profile']} profile)" if info.get("profile") else ""),
        "",
        f"- **Budget**: {budget_line}; seeds {', '.join(map(str, info['seeds']))}.",
        f"- **Problems**: {', '.join(info['problems'])}.",
        f"- **Candidate methods**: {', '.join(info['methods'])} (each problem runs those that apply).",
        "- **Settings** (`--set`; `problem.name` applies to that problem only): "
        + (
            ", ".join(f"`{k}={v}`" for k, v in settings.items())
            if settings
            else "none (every problem and method at its paper defaults)"
        ),
        f"- **Machine**: {m.get('cpu_count')} CPU cores ({m.get('usable_cpus')} usable by the process), "
        f"backend {m.get('backend')} ({m.get('device_kind')}; {len(m.get('devices', []))} device(s)), "
        f"JAX {versions.get('jax')}, jaxlib {versions.get('jaxlib')}, physgrad {versions.get('physgrad')}, "
        f"Python {m.get('python')}, {m.get('platform')}; started {m.get('time')}.",
        "",
        "The metric is each run's final test loss (as in `physgrad compare`); the seeds are the replicates, and a "
        "diverged or failed seed counts as +∞. Per method: the median over seeds with its 95 % bootstrap interval "
        "(n/a below 3 seeds). Rank: by the fraction of runs that diverged or failed, then by that median. "
        f"Ratio to {REFERENCE}: the median over seeds of the per-seed ratio. The comparison with each problem's best "
        'method pairs them by seed (`physgrad.harness.stats`): "seeds lower" counts the seeds on which the best '
        "method's mean over test cases is lower, and the two-sided Wilcoxon signed-rank p-value over seeds is given "
        "from 6 seeds on (below that it cannot reach 0.05).",
        "",
        "## Leaderboard",
        "",
        f"Geometric mean of the ratio to {REFERENCE} over the problems where both have a result (below 1: lower "
        "loss than Adam at the same budget); wins: problems where the method ranks first. Ordered by the score: "
        f"the same geometric mean, with a problem where every run of the method diverged or failed counting as a "
        f"ratio of {RATIO_CLIP[1]:g} (so a method cannot lead on the few problems where it converged).",
        "",
        markdown(board_lines(board)) if board else "(no runs yet)",
        "",
        "![method x problem heat map](heatmap.png)",
        "",
        "Heat map: log10 of the ratio to Adam (blue: lower loss); † some seeds diverged or failed; hatched: every "
        "run diverged or failed; blank: not applicable, skipped or not run; n/a: Adam has no result. Ratios enter "
        f"the logarithms clipped to [{RATIO_CLIP[0]:g}, {RATIO_CLIP[1]:g}] (a loss of exactly 0 has ratio 0).",
        "",
    ]
    for problem, table in tables.items():
        out += [f"## {problem}", "", markdown(table_lines(table)), ""]
        out += [f"Curves: [{problem}/loss_vs_time.png]({problem}/loss_vs_time.png); "
                f"files: `{problem}/summary.csv`, `{problem}/paired_tests.csv`, `{problem}/bench_table.csv`.", ""]  # fmt: skip
    out += [
        "## Longer budgets",
        "",
        "    physgrad bench --seconds 600 --seeds 5 --out bench-long",
        "",
        "runs every shipped problem with every applicable method for 10 minutes of training per run and 5 seeds "
        "(the same command again resumes it; `--problems a,b` and `--methods x,y` narrow it).",
        "",
    ]
    return "\n".join(out)

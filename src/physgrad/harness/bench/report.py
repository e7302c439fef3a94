"""A bench's report, (re)written from its files alone: every problem's table, the leaderboard,
the heat map and ``bench.md`` (see :mod:`physgrad.harness.bench` for the layout)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

from ...engine import rundir
from ...engine.rundir import atomic_write
from .. import plots, targets
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
    """The bench's tables (``{problem: method rows}``), final-loss leaderboard, written files
    and the time-to-target performance profile (``profile``: per method its ρ values and
    scores, :func:`profile_board`)."""

    tables: dict[str, list[dict[str, Any]]]
    board: list[dict[str, Any]]
    files: dict[str, Path | None]  # the figures' are None where they could not be drawn (a FigureWarning)
    profile: list[dict[str, Any]] = []

    @property
    def lines(self) -> list[list[str]]:
        """The final-loss leaderboard's printable lines."""
        return board_lines(self.board)

    @property
    def profile_lines(self) -> list[list[str]]:
        """The performance profile's printable lines (the leaderboard by time-to-target)."""
        return targets.profile_lines(self.profile)


def problem_table(out: str | Path, verdicts: Sequence[Verdict]) -> list[dict[str, Any]]:
    """One problem's method rows from its study directory, with the paired tests against
    the best method (written to its ``paired_tests.csv``: metric ``loss``, best first) and
    its loss-vs-time figure redrawn. A study kept without its runs (``keep_studies.py``:
    ``summary.csv``, ``results.csv``, ``study.json``...) gives the same rows from those files,
    and its kept ``paired_tests.csv`` where it has one (no runs: nothing to pair again)."""
    out = Path(out)
    runs = (out / "runs").exists()  # else not started, or kept without its runs (keep_studies.py)
    if runs:
        collect(out)  # the files may predate runs finished since (or a bench interrupted)
    rows = read_csv(out / "summary.csv") if (out / "summary.csv").exists() else []
    table = method_rows(rows, verdicts, read_failures(out))
    target, _, times = targets.study_times(out) if rows else (None, [], [])
    by_method = {t["method"]: t for t in times}
    for t in table:  # time-to-target: the median over seeds (+inf: not reached on half the seeds or more)
        ttt = by_method.get(t["method"])
        t["target"] = target.loss if target else math.nan
        t["ttt"] = ttt["time"]["median"] if ttt else math.inf
        t["ttt_low"], t["ttt_high"] = (ttt["time"]["low"], ttt["time"]["high"]) if ttt else (math.nan, math.nan)
        t["ttt_reached"] = f"{ttt['reached']}/{ttt['seeds']}" if ttt else ""
        t["ttt_cell"] = targets.median_time_cell(ttt) if ttt else ""
        t["budget_time"] = ttt["budget_time"] if ttt else math.nan
    tests = []
    if rows:
        study_report(out)  # loss_vs_time.png, as compare draws it
        best = best_method(table)
        others = [t["method"] for t in table if t["method"] != best and t["finished"]]
        if runs:
            if best and others:
                tests = paired_tests(out, metric="loss", order=[best, *others])
        elif (out / "paired_tests.csv").exists():  # kept without its runs' test cases: the tests as run
            tests = read_csv(out / "paired_tests.csv")
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
    info = rundir.read_json(out / "bench.json", rundir.NOT_A_STUDY)
    tables, files = {}, {}
    for problem in info["problems"]:
        verdicts = [Verdict(**v) for v in info["verdicts"][problem]]
        table = problem_table(out / problem, verdicts)
        tables[problem] = table
        (out / problem).mkdir(exist_ok=True)  # a bench interrupted before this problem: its table says pending
        write_csv(out / problem / "bench_table.csv", TABLE_COLUMNS, table_records(problem, table))
        atomic_write(out / problem / "bench_table.md", markdown(table_lines(table)) + "\n")
    board = leaderboard(tables)
    taus, rho, profile = profile_board(tables, board)
    write_csv(out / "leaderboard.csv", BOARD_COLUMNS, board_records(board))
    write_csv(out / "profile.csv", ["tau", *rho], [{"tau": f"{tau:.6g}", **{m: f"{v[i]:.4g}" for m, v in rho.items()}}
                                                   for i, tau in enumerate(taus)])  # fmt: skip
    atomic_write(out / "leaderboard.md", "## Performance profile (time to target)\n\n"
                 + markdown(targets.profile_lines(profile)) + "\n\n## Final test loss\n\n"
                 + markdown(board_lines(board)) + "\n")  # fmt: skip
    write_csv(out / "bench_table.csv", TABLE_COLUMNS, [r for p, t in tables.items() for r in table_records(p, t)])
    files["leaderboard"] = out / "leaderboard.csv"
    files["table"] = out / "bench_table.csv"
    files["markdown"] = out / "bench.md"
    files["profile"] = out / "profile.csv"
    atomic_write(out / "bench.md", bench_markdown(info, tables, board, profile))
    files["heatmap"] = plots.draw(  # last: a failing figure is a warning, the tables are written
        heatmap, tables, out / "heatmap.png", title=f"{_budget_text(info)}: final test loss relative to {REFERENCE}"
    )
    files["profile_figure"] = plots.draw(
        plots.performance_profile, taus, rho, out / "profile.png",
        title=f"{_budget_text(info)}: performance profile of the time to each problem's target test loss",
    )  # fmt: skip
    return BenchReport(tables, board, files, profile)


def profile_board(
    tables: dict[str, Sequence[dict[str, Any]]], board: Sequence[dict[str, Any]] = ()
) -> tuple[list[float], dict[str, list[float]], list[dict[str, Any]]]:
    """The performance profile of the bench's time-to-target medians (``t["ttt"]`` of each
    problem's method rows, :func:`problem_table`; :mod:`physgrad.harness.targets`): the τ
    grid, ρ per method, and per method its row of the profile table (ρ(1), ρ(2), ρ(10),
    problems solved, the geometric-mean score and, from ``board``, the final-loss score),
    sorted by the geometric-mean score (unscored last), then by problems solved."""
    methods = list(dict.fromkeys(t["method"] for table in tables.values() for t in table
                                 if t["status"] not in ("not applicable", "skipped")))  # fmt: skip
    times = {p: {t["method"]: t.get("ttt", math.inf) for t in table} for p, table in tables.items()}
    budgets = {p: max([t.get("budget_time", math.nan) for t in table if math.isfinite(t.get("budget_time", math.nan))],
                      default=math.nan) for p, table in tables.items()}  # fmt: skip
    ran = {m: {p for p, table in tables.items() for t in table
               if t["method"] == m and t["status"] not in ("not applicable", "skipped", "pending")} for m in methods}  # fmt: skip
    taus = targets.default_taus(times, methods)
    rho = targets.profile(times, methods, taus)
    scores = targets.scores(times, methods, budgets, ran)
    loss = {b["method"]: b["score"] for b in board}
    # ρ at the table's τ among all the methods (each against the fastest of them, not itself)
    at = targets.profile(times, methods, [1.0, 2.0, 10.0])
    rows = [{"method": m, **scores[m], "rho1": at[m][0], "rho2": at[m][1], "rho10": at[m][2],
             "loss_score": loss.get(m, math.nan)} for m in methods]  # fmt: skip
    rows.sort(key=lambda b: (math.isnan(b["score"]), b["score"] if not math.isnan(b["score"]) else 0, -b["solved"]))
    return taus, rho, rows


def _budget_text(info: dict[str, Any]) -> str:
    budget = ", ".join(f"{v:g} {k}" for k, v in info["budget"].items())
    seeds = len(info["seeds"])
    return f"{budget} per run, {seeds} seed{'s' if seeds != 1 else ''}"


def bench_markdown(
    info: dict[str, Any],
    tables: dict[str, Sequence[dict[str, Any]]],
    board: Sequence[dict[str, Any]],
    profile: Sequence[dict[str, Any]] = (),
) -> str:
    """``bench.md``: budgets, machine, settings, leaderboard, heat map and every problem's table."""
    m = info.get("machine", {})
    versions = m.get("versions", {})
    budget = info["budget"]
    kind = next(iter(budget))
    budget_line = {
        "seconds": (f"{budget[kind]:g} s of calibrated training time per run (each method's compiled step timed "
                    "first, `calibration.json` in each problem's directory; the run trains for seconds / calibrated "
                    "seconds per step steps), the same for every method of a problem"
                    if info.get("calibrated") else
                    f"{budget[kind]:g} s of training wall-clock per run (evaluation and compilation excluded), "
                    "the same for every method of a problem"),
        "steps": f"{budget[kind]:g} training steps per run",
        "epochs": f"{budget[kind]:g} epochs per run",
    }[kind]  # fmt: skip
    settings = info.get("settings") or {}
    if info.get("budgets"):
        budget_line += "; except " + ", ".join(
            f"{p}: {', '.join(f'{v:g} {k}' for k, v in b.items())}" for p, b in info["budgets"].items()
        )
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
        "## Performance profile: time to each problem's target",
        "",
        "Each problem declares a target test loss (`physgrad.harness.papers`, with its origin: a paper's level or "
        "ours). A run's time-to-target is the calibrated time of its first evaluation at or below the target (no "
        "interpolation); a run that never gets there is censored (+∞), a diverged run counts as never reaching it; "
        "per method the median over seeds. ρ(τ): the fraction of all problems on which a method's time-to-target is "
        "within τ of the fastest method's (Dolan–Moré); ρ(∞) the fraction it solved. The geometric-mean time ratio is "
        "over the problems the method ran where some method reached the target, an unsolved one counting as twice "
        "its budget over the fastest time; sorted by it.",
        "",
        markdown(targets.profile_lines(profile)) if profile else "(no runs yet)",
        "",
        "![performance profile](profile.png)",
        "",
        "## Leaderboard by final test loss",
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
        target = targets.target_of(problem)
        if target is not None:
            reached = [f"{t['method']} {t['ttt_cell']}" for t in table if t.get("ttt_cell")]
            out += [f"Target: test loss ≤ {target.loss:g} ({target.origin}: {target.why}). Time to target, median "
                    f"over seeds: {'; '.join(reached) or 'no runs yet'}.", ""]  # fmt: skip
        if any(t["runs"] > t["failed"] for t in table):  # curves are drawn from summary.csv's runs only
            out += [f"Curves: [{problem}/loss_vs_time.png]({problem}/loss_vs_time.png); "
                    f"files: `{problem}/summary.csv`, `{problem}/paired_tests.csv`, `{problem}/bench_table.csv`.", ""]  # fmt: skip
        else:
            out += ["Curves: none yet (no finished runs).", ""]
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

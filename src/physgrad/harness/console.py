"""The command line's one table printer and its list of files written, shared by the
commands' bodies (:mod:`physgrad.harness.study.console`, :mod:`physgrad.harness.bench.console`,
:mod:`physgrad.harness.tune_cli`)."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table
from rich.text import Text


def print_table(console: Console, lines: list[list[str]], title: str = "", caption: str = ""):
    """A table of plain text (cells such as ``[n/a: 2 seeds]`` are not rich markup)."""
    table = Table(title=title or None, caption=caption or None)
    for i, name in enumerate(lines[0]):
        table.add_column(Text(name), justify="left" if i == 0 else "right")
    for line in lines[1:]:
        table.add_row(*(Text(cell) for cell in line))
    console.print(table)


def files(*paths) -> str:
    """The files written, comma-separated (a figure that could not be drawn is None: left out)."""
    return ", ".join(str(p) for p in paths if p is not None)


def describe_run(summary: dict) -> str:
    """One line about a finished run."""
    if summary["status"] == "diverged":
        return f"diverged at step {summary['diverged_step']} (last finite loss {summary['last_finite_loss']})"
    failures = (summary.get("step_stat_totals") or {}).get("inverse_failures", 0)
    return (
        f"test loss {summary['final_test_loss']:.3e} after {summary['steps']} steps "
        f"({1e3 * summary['time_per_step']:.2f} ms/step)"
        + (f"; {failures:.0f} local inverse solves failed (their samples got no update)" if failures else "")
    )

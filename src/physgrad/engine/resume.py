"""What a run directory already holds, read before a run builds anything: whether it is
this run (:func:`recorded`), whether its budget is met (:func:`done_already`,
:func:`budget_met`), which of a finished run's files are missing, and its environment
record (:func:`write_environment`, kept from the run's start across resumes).

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import ConfigError, RunDirectoryExists, RunDirectoryRefused
from . import record as records
from . import rundir
from .recording import is_final, kept_path, read_json, read_summary, write_json
from .types import Budget, Epochs

# What a run directory may hold before its config.json: a study's record of a run that failed
# before it began (harness/failures.py writes traceback.txt there).
EARLY_RUN_FILES = ("traceback.txt",)
FINAL_FILES = ("params.eqx", "test_cases.json")  # written after the final checkpoint, before the summary


def write_environment(run_dir: Path, now: dict[str, Any]) -> None:
    """``env.json``: the environment that started the run, kept on every resume, with each
    resume's time, physgrad version and devices appended under ``resumed``."""
    path = run_dir / "env.json"
    try:
        started = read_json(path) if path.exists() else None
    except ConfigError:
        started = None  # a damaged env.json: this environment starts the record again
    if started is None:
        write_json(path, now)
        return
    resumed = {"time": now.get("time"), "physgrad": (now.get("versions") or {}).get("physgrad"),
               "devices": now.get("devices"), "threads": now.get("threads")}  # fmt: skip
    write_json(path, {**started, "resumed": [*started.get("resumed", []), resumed]})


def recorded(request: Any) -> dict[str, Any] | None:
    """The record (``config.json``) of the run already in the directory, None for a new
    run (or a run in memory); refused unless the caller resumes that same run. A directory
    that holds other files but no ``config.json`` (a study, someone's results) is refused:
    a run would overwrite them."""
    run_dir = request.run_dir
    if run_dir is None:
        return None
    if not (run_dir / "config.json").exists():
        names = (p.name for p in run_dir.iterdir()) if run_dir.is_dir() else ()
        foreign = sorted(n for n in names if not n.startswith(".") and n not in EARLY_RUN_FILES)
        if foreign:
            shown = ", ".join(foreign[:3]) + (", …" if len(foreign) > 3 else "")
            raise RunDirectoryRefused(
                f"{run_dir} holds files that are not a physgrad run ({shown}); a run would overwrite them: "
            )
        return None
    path = run_dir / "config.json"
    if not request.resume:
        raise RunDirectoryExists(run_dir)
    old = read_json(path)
    verdict = request.same_run(old)
    if verdict is True or (not isinstance(verdict, bool) and not list(verdict)):
        return old
    differ = records.differences(records.identity(old), records.identity(records.like(json.loads(json.dumps(request.record, default=str)), old))) \
        if isinstance(verdict, bool) else list(verdict)  # fmt: skip
    what = f" ({'; '.join(differ[:6])}{'; …' if len(differ) > 6 else ''})" if differ else ""
    raise RunDirectoryRefused(
        f"run directory {run_dir} holds a different configuration{what}; resume it with its own settings or "
    )


def done_already(run_dir: Path, budget: Budget, wall_cap: float = 0.0) -> dict[str, Any] | None:
    """The summary of a run that needs nothing more for ``budget`` (diverged, or finished
    exactly at it, or stopped by a wall-clock cap that ``wall_cap`` does not raise), read
    before any work; None if it must train on or finish (a ``summary.json`` without its
    final losses, as an older physgrad wrote after a resume, is finished again from the
    checkpoint)."""
    summary = read_summary(run_dir)
    if summary is None or not is_final(summary):
        return None
    missing = missing_final_files(run_dir)
    if missing:  # deleted since: made again from the final checkpoint, where there is one
        if rundir.checkpoint_path(run_dir) is not None:
            return None
        raise ConfigError(f"the run in {run_dir} finished but its {' and '.join(missing)} "
                          f"{'is' if len(missing) == 1 else 'are'} missing and it has no checkpoint to make "
                          f"{'it' if len(missing) == 1 else 'them'} again from; remove the run directory and run "
                          "it again")  # fmt: skip
    if summary["status"] == "diverged":
        return summary
    if summary.get("wall_capped") and wall_cap > 0 and summary.get("train_seconds", 0.0) >= wall_cap:
        if summary.get("budget") == budget.to_dict():
            return summary
    if not isinstance(summary.get("steps"), int):
        return None
    met = budget_met(budget, recorded=summary.get("budget"), step=summary["steps"],
                      seconds=summary.get("train_seconds", 0.0), epochs=None, run_dir=run_dir)  # fmt: skip
    return summary if met else None


def missing_final_files(run_dir: Path) -> list[str]:
    """The files of a finished run (:data:`FINAL_FILES`, plain or packed) that are missing."""
    return [name for name in FINAL_FILES if not kept_path(run_dir / name).exists()]


def budget_met(
    budget: Budget, *, recorded: Any, step: int, seconds: float, epochs: Callable[[int], float] | None, run_dir: Path
) -> bool | None:
    """Whether a run at ``step`` (after ``seconds`` of training) is done with ``budget``:
    False (train on), True (met at exactly this step, or ``budget`` is the ``recorded`` one
    it ran to), None (cannot tell without ``epochs``, the data's step-to-epoch map). A budget
    the run went past is refused: a resumed run cannot undo steps."""
    if epochs is None and isinstance(budget, Epochs):
        return True if recorded == budget.to_dict() else None
    epochs_at = epochs or (lambda step: math.nan)  # called for an epochs budget only, which has it
    if not budget.met(step, seconds, epochs_at):
        return False
    if recorded == budget.to_dict() or budget.first_met_at(step, epochs_at):
        return True
    what = budget.spent(step, seconds, epochs_at)
    trained = (
        f"the run in {run_dir} has already trained {what}, more than the budget of {budget}; resume it with at least"
    )
    raise RunDirectoryRefused(f"{trained} that budget, or ")

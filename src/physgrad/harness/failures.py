"""The failure log of a study: runs that raised, recorded so that the study goes on.

``physgrad.harness.study.compare(..., record_failures=True)`` (and so every bench problem) records
a run that raises (:func:`recordable`: not bad input) and goes on; it keeps
``OUT/failures.json``, ``{run name: {"method", "seed", "error", "traceback"}}`` with the
error in one line, and the full traceback in ``OUT/runs/<run name>/traceback.txt``. A run
that raises stays unfinished, so running the study again tries it again (the cause, e.g.
a memory refusal, may have gone); an entry is removed once its run finishes, and entries
of runs the current plan does not list are dropped (a directory reused with other
settings). Every write replaces the file all at once: a kill never leaves half of it.
"""

from __future__ import annotations

import json
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..engine import rundir
from ..errors import ConfigError, DoesNotFit

FAILURES = "failures.json"
TRACEBACK = "traceback.txt"


def one_line(e: BaseException) -> str:
    """An exception's message on one line (its type's name where it has none)."""
    text = str(e).strip() or type(e).__name__
    return " ".join(text.split())


def recordable(error: Exception) -> bool:
    """Whether a study that records failures records ``error`` and goes on: every exception
    but a :class:`ConfigError`, which is the user's input to fix before anything else runs;
    the memory guard's :class:`DoesNotFit` is one too, but it depends on the method and the
    machine, so another method of the study may well fit."""
    return isinstance(error, DoesNotFit) or not isinstance(error, ConfigError)


def read_failures(out: str | Path) -> dict[str, dict[str, Any]]:
    """A study's ``failures.json``: {run name: {method, seed, error[, traceback]}}; {} if absent."""
    path = Path(out) / FAILURES
    return rundir.read_json(path, f"remove {path} to record the study's failures afresh", empty={})


class FailureLog:
    """The failures of the runs a study plans (``names``), read from ``out`` and kept there.

    ``write`` says whether the file is written even when it has no entries (a study that
    records failures always leaves one; one that does not only keeps an existing file
    current, so that a run finished since is no longer listed as failed)."""

    def __init__(self, out: str | Path, names: Sequence[str], *, write: bool):
        self.out = Path(out)
        self.entries = {k: v for k, v in read_failures(self.out).items() if k in set(names)}
        self.write = write or (self.out / FAILURES).exists()
        self.save()

    def save(self) -> None:
        if self.write:
            rundir.atomic_write(self.out / FAILURES, json.dumps(self.entries, indent=2, default=str) + "\n")

    def record(self, name: str, method: str, seed: int, error: Exception) -> str:
        """Record that run ``name`` raised ``error``; return the one-line error."""
        run_dir = self.out / "runs" / name
        run_dir.mkdir(parents=True, exist_ok=True)  # a run refused before it made its directory
        text = "".join(traceback.format_exception(type(error), error, error.__traceback__))
        rundir.atomic_write(run_dir / TRACEBACK, text)
        line = f"{type(error).__name__}: {one_line(error)}"
        self.entries[name] = {"method": method, "seed": seed, "error": line, "traceback": f"runs/{name}/{TRACEBACK}"}
        self.write = True
        self.save()
        return line

    def clear(self, name: str) -> None:
        """Run ``name`` finished: its entry and traceback go (a stale one would count it as failed)."""
        (self.out / "runs" / name / TRACEBACK).unlink(missing_ok=True)
        if self.entries.pop(name, None) is not None:
            self.save()

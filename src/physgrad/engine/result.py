"""What :func:`physgrad.fit` returns: :class:`FitResult` (the summary, the history of every
evaluation as arrays, the final network and state), and the history made from evaluation
rows (:func:`history_of`) or read back from a run directory's ``metrics.csv``
(:func:`history_from_metrics`).

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .packed import kept_path, read_metrics

# An evaluation as the history holds it: (step, training seconds, {metric: value}).
Row = tuple[int, float, dict[str, float]]


def history_of(rows: Sequence[Row]) -> dict[str, np.ndarray]:
    """The evaluations ``rows`` as columns: ``step`` (int64, shape ``(E,)``), ``time``
    (float64, training seconds at the evaluation: compilation and evaluation excluded) and
    one float64 array of shape ``(E,)`` per metric, NaN where an evaluation lacks it (the
    step statistics and ``train_time_per_step`` start after step 0). Columns are ordered
    ``step``, ``time``, then the metrics by name.

    Why columns of equal length: ``pandas.DataFrame(history)`` and ``plt.plot(h["step"],
    h["test_loss"])`` take them as they are."""
    names = sorted({name for _, _, metrics in rows for name in metrics})
    columns: dict[str, np.ndarray] = {
        "step": np.array([step for step, _, _ in rows], np.int64),
        "time": np.array([seconds for _, seconds, _ in rows], np.float64),
    }
    for name in names:
        columns[name] = np.array([metrics.get(name, math.nan) for _, _, metrics in rows], np.float64)
    return columns


def rows_from_metrics(records: Sequence[Mapping[str, Any]]) -> list[Row]:
    """``metrics.csv``'s long rows (``step``, ``wall_time``, ``split``, ``metric``, ``value``;
    strings or numbers) as evaluation rows, one per step in order of step."""
    by_step: dict[int, tuple[float, dict[str, float]]] = {}
    for r in records:
        step = int(r["step"])
        seconds, metrics = by_step.setdefault(step, (float(r["wall_time"]), {}))
        metrics[f"{r['split']}_{r['metric']}"] = float(r["value"])
    return [(step, seconds, metrics) for step, (seconds, metrics) in sorted(by_step.items())]


def history_from_metrics(path: str | Path) -> dict[str, np.ndarray]:
    """A run directory's ``metrics.csv`` as :func:`history_of`'s columns (empty columns
    ``step`` and ``time`` if it has no file)."""
    path = Path(path)  # a finished run's curves may be kept gzipped (read_metrics reads them)
    return history_of(rows_from_metrics(read_metrics(path)) if kept_path(path).exists() else [])


@dataclasses.dataclass(frozen=True, eq=False)
class FitResult(dict[str, Any]):
    """What :func:`physgrad.fit` returns.

    Fields:
        summary: the run's summary (``status``, ``steps``, ``final_test_loss``, ...; also
            ``summary.json`` where the run writes a directory).
        history: every evaluation as arrays of shape ``(E,)`` (:func:`history_of`):
            ``step``, ``time`` and the metrics (``train_loss``, ``test_loss``, ``val_*``,
            ``train_step_<statistic>`` averaged since the previous evaluation,
            ``train_time_per_step``, ...). ``pandas.DataFrame(result.history)`` is a table.
        network: the final network (parameters and structure, host arrays), or None for a
            resumed run that was complete already (``physgrad.load_network(out, like=...)``
            reads it from ``params.eqx``).
        state: the final :class:`~physgrad.TrainState` (parameters, optimizer state,
            counters), or None as ``network``.
        run_dir: the run directory, or None for a run in memory (``out=None``).

    The result also reads as the summary, as ``fit`` returned it before the result had a
    history: ``result["status"]``, ``dict(result)`` and ``result == summary`` work, and
    ``json.dumps(result)`` writes the summary (a read-only ``dict`` of it: changing an entry
    is refused, so the two never disagree). :meth:`to_dict` adds the history and the run
    directory, as plain lists and strings that ``json.dumps`` takes.
    """

    summary: dict[str, Any]
    history: dict[str, np.ndarray]
    network: Any = None
    state: Any = None
    run_dir: Path | None = None

    def __post_init__(self):
        dict.update(self, self.summary)

    def to_dict(self) -> dict[str, Any]:
        """``{"summary": ..., "history": {name: [E values]}, "run_dir": str | None}``: the
        result without its arrays' types (the network and the state stay out: they are
        arrays; ``params.eqx`` holds the network of a run with a directory)."""
        return {
            "summary": copy.deepcopy(self.summary),
            "history": {name: np.asarray(column).tolist() for name, column in self.history.items()},
            "run_dir": None if self.run_dir is None else str(self.run_dir),
        }

    def _read_only(self, *args, **kwargs):
        raise TypeError("a FitResult is read-only (it reads as its summary); copy it first: dict(result)")

    __setitem__ = __delitem__ = __ior__ = _read_only  # pyright: ignore[reportAssignmentType]
    clear = pop = popitem = setdefault = update = _read_only  # pyright: ignore[reportAssignmentType]

    def __reduce__(self):  # pickle and copy rebuild it from its fields, not item by item
        return (type(self), (self.summary, self.history, self.network, self.state, self.run_dir))

    def __repr__(self) -> str:
        where = "in memory" if self.run_dir is None else str(self.run_dir)
        metrics = ", ".join(k for k in self.history if k not in ("step", "time"))
        evaluations = len(self.history.get("step", ()))
        return (f"FitResult(status={self.summary.get('status')!r}, steps={self.summary.get('steps')}, "
                f"{where}, history: {evaluations} evaluations of {metrics})")  # fmt: skip

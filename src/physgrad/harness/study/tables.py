"""A study's tables: ``results.csv`` (every run's metrics, long format) and ``summary.csv``
(one row per run) gathered from its run directories (:func:`collect`), and the CSV reading
and writing they share with the bench, the sweeps and the tuner, plain or gzipped."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ...engine import rundir
from ...engine.recording import gzip_bytes, open_kept, packed_path
from ...errors import ConfigError
from ..train import read_metrics, read_summary

SUMMARY_COLUMNS = (
    "problem", "method", "seed", "status", "steps", "epochs", "train_seconds", "time_per_step",
    "final_train_loss", "final_test_loss", "best_test_loss", "diverged_step", "last_finite_loss",
    "compile_seconds", "run_dir", "calibrated_seconds", "calibrated_ms_per_step", "wall_capped",
    "cpu_time_per_step", "calibration_clock",
)  # fmt: skip
CPU_COLUMNS = ("cpu_time_per_step", "calibration_clock")  # SUMMARY_COLUMNS' last, added with the CPU clock
RESULT_COLUMNS = ("problem", "method", "seed", "step", "wall_time", "split", "metric", "value", "calibrated_time")


def collect(out: str | Path) -> list[dict[str, Any]]:
    """Gather the runs of a study into ``results.csv`` and ``summary.csv`` (only the runs
    that ``study.json`` plans, when it lists them: a directory reused with another budget or
    setting keeps the old runs' directories, which must not mix into the tables)."""
    from ..calibration import read as read_calibration

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
            # the timer of calibrated_ms_per_step: the in-run time_per_step (wall) or cpu_time_per_step it compares with
            row["calibration_clock"] = calibration.record.get("clock", "wall")  # type: ignore[union-attr]
        rows.append(row)
        try:
            metrics = read_metrics(run_dir / "metrics.csv")
        except (OSError, ValueError, KeyError, TypeError, EOFError, csv.Error) as e:
            raise ConfigError(f"{run_dir / 'metrics.csv'} cannot be read ({type(e).__name__}); "
                              f"{rundir.RUN_DAMAGED}") from None  # fmt: skip
        results += [{**ident, **r, **({"calibrated_time": clock(r["step"])} if clock else {})} for r in metrics]
    # the in-run CPU columns only where a run measured one: a study collected again before
    # them (a committed one) keeps its table as it was
    timed = any(r.get("cpu_time_per_step") is not None for r in rows)
    write_csv(out / "summary.csv", SUMMARY_COLUMNS if timed else SUMMARY_COLUMNS[: -len(CPU_COLUMNS)], rows)
    write_csv(out / "results.csv", RESULT_COLUMNS, results)
    return rows


def write_csv(path: Path, columns: Sequence[str], rows: list[dict[str, Any]]):
    """A table written all at once (:func:`physgrad.engine.rundir.atomic_write`; never half). A
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


def diverged_seeds(rows: list[dict[str, Any]]) -> dict[str, set[str]]:
    """{method: the seeds (as text) whose runs diverged}, for the figures' marks."""
    out: dict[str, set[str]] = {}
    for r in rows:
        if r["status"] == "diverged":
            out.setdefault(r["method"], set()).add(str(r["seed"]))
    return out

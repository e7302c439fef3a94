"""The calibration's table and conditions: the machine and its load a calibration ran on,
and ``calibration.csv``, one row per stage of every calibrated method in the columns of
the long studies' table (:mod:`physgrad.harness.calibration` times the steps)."""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..engine import rundir

# The columns of docs/reproductions/long/calibration.csv (the long-study lanes' table),
# then the spread and conditions of each measurement.
CSV_COLUMNS = ("problem", "method", "route", "batch", "ms_per_step", "measured", "machine", "command")
EXTRA_COLUMNS = ("spec", "stage", "ms_q25", "ms_q75", "ms_min", "ms_max", "rounds", "compile_seconds", "threads",
                 "load")  # fmt: skip


def machine() -> dict[str, Any]:
    """What the budgets were spent on: CPU cores (all, and usable by this process), JAX's
    backend and devices, versions (``engine.environment``)."""
    from ..engine import environment

    env = environment()
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        usable = os.cpu_count()
    import jax

    kinds = sorted({getattr(d, "device_kind", d.platform) for d in jax.devices()})
    return {**env, "usable_cpus": usable, "device_kind": ", ".join(kinds)}


def load() -> list[float] | None:
    """The machine's 1, 5 and 15 minute load averages (None where the OS has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def machine_line(record: Mapping[str, Any]) -> str:
    """The machine column of the calibration table: cores, usable cores, device, threads, load."""
    m = record.get("machine") or {}
    load_text = ", ".join(f"{x:g}" for x in record.get("load_before") or []) or "unknown"
    threads = record.get("threads")
    return (f"{m.get('cpu_count', '?')} CPU cores ({m.get('usable_cpus', '?')} usable), {m.get('device_kind', '?')}; "
            f"threads {threads if threads is not None else 'default'}; load {load_text}")  # fmt: skip


def csv_rows(calibration: Any, specs: Sequence[str] | None = None, command: str = "") -> list[dict[str, Any]]:
    """One row per stage of every calibrated method of ``calibration`` (a
    :class:`physgrad.harness.calibration.Calibration`; not imported: that module imports this
    one), in the long-study table's columns (:data:`CSV_COLUMNS`) followed by the spread and
    conditions (:data:`EXTRA_COLUMNS`)."""
    record = calibration.record
    rows = []
    for spec in specs or list(record["methods"]):
        for i, s in enumerate(calibration.stages(spec)):
            entry = record["methods"][spec]
            rows.append({
                "problem": record.get("problem"), "method": s.method, "route": s.route, "batch": s.batch_size,
                "ms_per_step": f"{1e3 * s.seconds:.4g}", "measured": str(entry.get("measured", record["measured"]))[:10],
                "machine": machine_line(record), "command": command or f"physgrad compare {record.get('problem')} (calibration)",
                "spec": spec, "stage": i, "ms_q25": f"{1e3 * s.q25:.4g}", "ms_q75": f"{1e3 * s.q75:.4g}",
                "ms_min": f"{1e3 * s.low:.4g}", "ms_max": f"{1e3 * s.high:.4g}", "rounds": s.rounds,
                "compile_seconds": f"{s.compile_seconds:.3g}", "threads": record.get("threads"),
                "load": " ".join(f"{x:g}" for x in entry.get("load") or record.get("load_before") or []),
            })  # fmt: skip
    return rows


def write_csv(path: str | Path, rows: list[dict[str, Any]]) -> None:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=[*CSV_COLUMNS, *EXTRA_COLUMNS], extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    rundir.atomic_write(Path(path), text.getvalue())


__all__ = ["CSV_COLUMNS", "EXTRA_COLUMNS", "csv_rows", "load", "machine", "machine_line", "write_csv"]

"""Run-directory files kept gzipped (kept results and finished runs' curves are committed
compressed) and reading them back whichever form they have: the one module that both the
recording (:mod:`physgrad.engine.recording`) and the result (:mod:`physgrad.engine.result`)
read them through, so that neither imports the other for them.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import csv
import gzip
import io
from pathlib import Path
from typing import Any

from . import rundir


def kept_path(path: str | Path) -> Path:
    """``path``, or its gzipped copy ``path.gz`` where only that exists (kept results and
    finished runs' curves are committed compressed: docs/reproductions/keep_studies.py
    --gzip, docs/reproductions/long/prune.py --pack)."""
    path = Path(path)
    packed = packed_path(path)
    return packed if not path.exists() and packed.exists() else path


def packed_path(path: str | Path) -> Path:
    """Where the gzipped copy of ``path`` is kept: ``path.gz`` beside it."""
    return Path(path).with_name(Path(path).name + ".gz")


def open_kept(path: str | Path) -> io.TextIOBase:
    """``path`` opened for reading as text, or its gzipped copy where only that exists
    (:func:`kept_path`); ``newline=""`` as the csv module wants. Typed as the concrete text
    stream both openers return (``typing.IO`` is not a runtime type for beartype's checks)."""
    path = kept_path(path)
    return (gzip.open if path.suffix == ".gz" else open)(path, "rt", encoding="utf-8", newline="")


def pack_file(source: str | Path, target: str | Path) -> Path:
    """``source`` gzipped to ``target``, the same bytes for the same file: no name or time in
    the gzip header, so that packing a kept file again changes nothing in git. Written all at
    once (:func:`physgrad.engine.rundir.atomic_write`), so ``target`` is never half-written;
    :func:`kept_path` finds it."""
    rundir.atomic_write(target, gzip_bytes(Path(source).read_bytes()))
    return Path(target)


def gzip_bytes(data: bytes) -> bytes:
    """``data`` gzipped with no name or time in the header: the same bytes give the same file."""
    packed = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=packed, mtime=0) as out:
        out.write(data)
    return packed.getvalue()


def read_metrics(path: Path) -> list[dict[str, Any]]:
    """``metrics.csv`` as a list of typed rows (from its gzipped copy where only that exists:
    :func:`kept_path`)."""
    with open_kept(path) as f:
        return [
            {"step": int(r["step"]), "wall_time": float(r["wall_time"]), "split": r["split"], "metric": r["metric"],
             "value": float(r["value"])}
            for r in csv.DictReader(f)
        ]  # fmt: skip

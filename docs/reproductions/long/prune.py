"""Remove the checkpoints of finished long-study runs from docs/reproductions/data.

A long-study run directory is committed as it grows, checkpoint included, so that a later
session resumes it. Once the run is final (its ``summary.json`` says finished with its final
losses, or diverged) the checkpoint has no reader: ``physgrad compare`` skips a finished run
from its summary alone, and ``long/report.py`` and ``sign_mask.py`` read ``metrics.csv``,
``summary.json``, ``config.json`` and ``params.eqx``. The checkpoints were a third of the
committed tree, which must stay small enough to travel to a lent GPU machine (64 MiB).

    python docs/reproductions/long/prune.py [--dry-run] [--pack STUDY ...] [--pack-finished]

deletes ``checkpoint/`` of every final run under docs/reproductions/data (runs in progress
keep theirs), prints what it removed and the size of the committed tree against that limit;
commit the deletions with the lane data. ``--pack`` also gzips the final runs' ``metrics.csv``
and ``test_cases.json`` (to ``….gz``, 2–5× smaller) in the named studies, and their
``results.csv`` tables (physgrad rewrites a table kept gzipped gzipped): only for a study
whose lane is done, since a lane at a physgrad older than the packed-file readers could not
re-collect them (physgrad's ``read_metrics`` and paired tests, and ``long/report.py``, read
the packed copies). ``--root`` points it at another tree of run directories (a bench such as
docs/benchmark/dense, whose studies are its problems); ``--pack-finished`` packs every
tuned-bench problem there whose test study is complete (``python
docs/reproductions/long/prune.py --root docs/benchmark/tuned --pack-finished`` after a lane
commit), so no finished problem's curves stay plain.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
from pathlib import Path

from physgrad.engine.recording import is_final, pack_file, packed_path

DATA = Path(__file__).resolve().parent.parent / "data"
LIMIT = 64 * 2**20  # the working tree a lent GPU machine accepts


def final_checkpoints(root: Path) -> list[Path]:
    """The ``checkpoint/`` directories of the final runs under ``root``."""
    found = []
    for checkpoint in sorted(root.rglob("checkpoint")):
        summary = checkpoint.parent / "summary.json"
        if checkpoint.is_dir() and summary.exists() and is_final(json.loads(summary.read_text())):
            found.append(checkpoint)
    return found


def final_runs(root: Path) -> list[Path]:
    """The run directories under ``root`` whose summary is final."""
    return [s.parent for s in sorted(root.rglob("summary.json")) if is_final(json.loads(s.read_text()))]


PACKED = ("metrics.csv", "test_cases.json")  # the files of a final run that --pack gzips


def pack_run(run: Path) -> int:
    """Gzip a final run's ``metrics.csv`` and ``test_cases.json`` (:func:`pack_table`); the
    bytes saved."""
    return sum(pack_table(run / name) for name in PACKED if (run / name).exists())


def pack_table(plain: Path) -> int:
    """Gzip ``plain`` to ``….gz`` beside it (no name or time in the header, so the same bytes
    every time) and remove the plain copy; the bytes saved. A study's ``results.csv`` packed
    so stays packed: collecting the study again rewrites the gzipped copy (``write_csv``)."""
    packed = packed_path(plain)
    pack_file(plain, packed)
    saved = plain.stat().st_size - packed.stat().st_size
    plain.unlink()
    return saved


def finished_tunes(root: Path) -> list[Path]:
    """The tuned-bench problems under ``root`` that are done: a tune directory (``tune.json``)
    whose test study ``final/`` has its ``summary.csv`` with one row per run directory and
    every one of those runs final. A problem whose trials or test runs are under way is not."""
    done = []
    for tune in sorted(root.rglob("tune.json")):
        final = tune.parent / "final"
        if not (final / "summary.csv").exists() or not (final / "runs").is_dir():
            continue
        runs = [r for r in (final / "runs").iterdir() if r.is_dir()]
        with (final / "summary.csv").open() as f:
            rows = sum(1 for _ in f) - 1
        summaries = [r / "summary.json" for r in runs]
        if runs and rows == len(runs) and all(s.exists() and is_final(json.loads(s.read_text())) for s in summaries):
            done.append(tune.parent)
    return done


def tracked_bytes(root: Path) -> int | None:
    """The size of the files git tracks in the checkout holding ``root`` (None without git)."""
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=root, capture_output=True, check=True)
        base = Path(top.stdout.decode().strip())
        names = subprocess.run(["git", "ls-files", "-z"], cwd=base, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    return sum((base / n).stat().st_size for n in names.decode().split("\0") if n and (base / n).is_file())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=DATA, help="where the run directories are (default: the data)")
    parser.add_argument("--dry-run", action="store_true", help="list what would go, remove nothing")
    parser.add_argument("--pack", nargs="+", default=[], metavar="STUDY",
                        help="also gzip the final runs' metrics.csv and test_cases.json, and every results.csv, "
                             "in these (finished) studies")  # fmt: skip
    parser.add_argument("--pack-finished", action="store_true",
                        help="also pack every finished tuned-bench problem under --root (its test study complete)")  # fmt: skip
    args = parser.parse_args()
    if args.pack_finished:
        args.pack += [str(t.relative_to(args.root)) for t in finished_tunes(args.root)]
    total = 0
    for checkpoint in final_checkpoints(args.root):
        size = sum(f.stat().st_size for f in checkpoint.rglob("*") if f.is_file())
        total += size
        if not args.dry_run:
            shutil.rmtree(checkpoint)
        print(
            f"{'would remove' if args.dry_run else 'removed'} {checkpoint.relative_to(args.root)} ({size / 1e3:.0f} kB)"
        )
    print(f"{total / 2**20:.1f} MiB of final runs' checkpoints {'to remove' if args.dry_run else 'removed'}")
    saved = 0
    for study in args.pack:
        if not (args.root / study).is_dir():
            raise SystemExit(f"no study {study!r} under {args.root}")
        for run in final_runs(args.root / study):
            saved += 0 if args.dry_run else pack_run(run)
        for table in sorted((args.root / study).rglob("results.csv")):
            saved += 0 if args.dry_run else pack_table(table)
    if args.pack and not args.dry_run:
        print(f"{saved / 2**20:.1f} MiB saved by packing {', '.join(PACKED)} and results.csv in {', '.join(args.pack)}")
    size = tracked_bytes(args.root)
    if size is not None:
        note = "" if size < LIMIT - 8 * 2**20 else " -- near the limit: prune or pack more before a GPU session"
        print(f"tracked files: {size / 2**20:.1f} MiB of the {LIMIT / 2**20:.0f} MiB a GPU machine accepts{note}")


if __name__ == "__main__":
    main()

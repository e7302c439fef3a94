"""Remove the checkpoints of finished long-study runs from docs/reproductions/data.

A long-study run directory is committed as it grows, checkpoint included, so that a later
session resumes it. Once the run is final (its ``summary.json`` says finished with its final
losses, or diverged) the checkpoint has no reader: ``physgrad compare`` skips a finished run
from its summary alone, and ``long/report.py`` and ``sign_mask.py`` read ``metrics.csv``,
``summary.json``, ``config.json`` and ``params.eqx``. The checkpoints were a third of the
committed tree, which must stay small enough to travel to a lent GPU machine (64 MiB).

    python docs/reproductions/long/prune.py [--dry-run]

deletes ``checkpoint/`` of every final run under docs/reproductions/data (runs in progress
keep theirs) and prints what it removed; commit the deletions with the lane data.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from physgrad.engine.recording import is_final

DATA = Path(__file__).resolve().parent.parent / "data"


def final_checkpoints(root: Path) -> list[Path]:
    """The ``checkpoint/`` directories of the final runs under ``root``."""
    found = []
    for checkpoint in sorted(root.rglob("checkpoint")):
        summary = checkpoint.parent / "summary.json"
        if checkpoint.is_dir() and summary.exists() and is_final(json.loads(summary.read_text())):
            found.append(checkpoint)
    return found


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=DATA, help="where the run directories are (default: the data)")
    parser.add_argument("--dry-run", action="store_true", help="list what would go, remove nothing")
    args = parser.parse_args()
    total = 0
    for checkpoint in final_checkpoints(args.root):
        size = sum(f.stat().st_size for f in checkpoint.rglob("*") if f.is_file())
        total += size
        if not args.dry_run:
            shutil.rmtree(checkpoint)
        print(f"{'would remove' if args.dry_run else 'removed'} {checkpoint.relative_to(args.root)} ({size / 1e3:.0f} kB)")
    print(f"{total / 2**20:.1f} MiB of final runs' checkpoints {'to remove' if args.dry_run else 'removed'}")


if __name__ == "__main__":
    main()

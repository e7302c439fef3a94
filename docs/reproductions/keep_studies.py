"""Copy the study-level result files of finished studies into the repository.

A study directory (``physgrad compare --out DIR``) holds its runs (parameters, checkpoints,
per-case test results) and a few small study-level files from which every table and figure of
the reproduction reports is drawn: ``summary.csv`` (one row per run), ``results.csv`` (every
evaluation of every run: the curves), ``study.json`` (problem, methods, settings, budget),
the calibration (``calibration.json|csv``: seconds per step of each method) and the tests
(``paired_tests.csv``, ``time_to_target.csv``). A sweep adds ``grid.json`` above its cells.

    python docs/reproductions/keep_studies.py studies/hig docs/reproductions/data/short/hig

copies those files of every study under the first directory (at any depth, keeping the
relative paths) to the second, and leaves the runs out. With ``--runs`` it also keeps each
run's small files (config, summary, metrics, per-test-case results, final parameters; not the
checkpoint), which unrolling_report.py reads (per-case paired tests, the learned stencils). The report scripts read them back:
``python docs/reproductions/hig_report.py`` redraws hig.md's tables and figures from a clone.
A bench's ``bench.json`` is kept too, merged into one already there (a bench run in
lanes, one directory each), so that ``physgrad report TARGET`` redraws the whole bench.
A study without ``summary.csv`` (not finished) is skipped with a line that says so.
With ``--gzip`` each ``results.csv`` is kept compressed as ``results.csv.gz`` (a sweep's curves,
every epoch of every run, are ≈ 1 MB per cell; ≈ 6× smaller packed); physgrad's ``read_csv``
reads either.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from physgrad.engine.recording import pack_file

STUDY_FILES = (
    "summary.csv", "results.csv", "study.json", "calibration.json", "calibration.csv",
    "paired_tests.csv", "time_to_target.csv", "grid.json",
)  # fmt: skip


def keep(source: Path, target: Path, runs: bool = False, packed: bool = False) -> list[Path]:
    """Copy the study-level files of each finished study under ``source`` to the same relative
    path under ``target`` (and, with ``runs``, every run's files but its checkpoint; with
    ``packed``, ``results.csv`` gzipped); return the copied files' targets."""
    copied = []
    for study in sorted(p.parent for p in source.rglob("study.json")):
        if "runs" in study.relative_to(source).parts:
            continue
        rel = study.relative_to(source)
        if not (study / "summary.csv").exists():
            print(f"{rel}: not finished (no summary.csv), skipped")
            continue
        for name in STUDY_FILES:
            if name == "results.csv" and not (study / name).exists() and (study / (name + ".gz")).exists():
                (target / rel).mkdir(parents=True, exist_ok=True)  # a kept study kept again: its curves packed
                copied.append(Path(shutil.copy2(study / (name + ".gz"), target / rel / (name + ".gz"))))
                (target / rel / name).unlink(missing_ok=True)
            elif (study / name).exists():
                (target / rel).mkdir(parents=True, exist_ok=True)
                if packed and name == "results.csv":
                    copied.append(pack_file(study / name, target / rel / (name + ".gz")))
                    (target / rel / name).unlink(missing_ok=True)  # one copy of the curves
                else:
                    copied.append(Path(shutil.copy2(study / name, target / rel / name)))
                    (target / rel / (name + ".gz")).unlink(missing_ok=True)
        for run in sorted((study / "runs").glob("*/")) if runs else ():
            (target / rel / "runs" / run.name).mkdir(parents=True, exist_ok=True)
            for f in run.iterdir():
                if f.is_file():  # the checkpoint directory stays behind
                    copied.append(Path(shutil.copy2(f, target / rel / "runs" / run.name / f.name)))
        print(f"{rel}: kept")
    for grid in source.rglob("grid.json"):  # a sweep's own record, above its cells
        rel = grid.relative_to(source)
        (target / rel.parent).mkdir(parents=True, exist_ok=True)
        copied.append(Path(shutil.copy2(grid, target / rel)))
    for info in source.rglob("bench.json"):  # a bench's own record, above its problems' studies
        rel = info.relative_to(source)
        (target / rel.parent).mkdir(parents=True, exist_ok=True)
        copied.append(keep_bench(info, target / rel))
    return copied


def keep_bench(source: Path, target: Path) -> Path:
    """Copy a bench's ``bench.json``; where ``target`` already holds one (the same bench split
    over lanes or machines, each with its own directory, gathered into one), add the source's
    problems, verdicts and per-problem budgets to it, so that ``physgrad report TARGET`` draws
    every problem gathered so far. The two must agree on methods, seeds, budget, profile and
    the settings they share (a profile's settings differ by problem)."""
    new = json.loads(source.read_text())
    if not target.exists():
        shutil.copy2(source, target)
        return target
    old = json.loads(target.read_text())
    clash = [k for k in ("methods", "seeds", "budget", "profile") if old.get(k) != new.get(k)]
    clash += [f"setting {k}" for k, v in new.get("settings", {}).items() if old.get("settings", {}).get(k, v) != v]
    if clash:
        raise SystemExit(f"{source} and {target} are different benches: their {', '.join(clash)} differ")
    old["settings"] = {**old.get("settings", {}), **new.get("settings", {})}
    old["problems"] = list(dict.fromkeys([*old["problems"], *new["problems"]]))
    old["verdicts"] = {**old["verdicts"], **new["verdicts"]}
    old["budgets"] = {**old.get("budgets", {}), **new.get("budgets", {})}
    target.write_text(json.dumps(old, indent=2) + "\n")
    return target


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="directory holding study directories (e.g. studies/hig)")
    parser.add_argument("target", type=Path, help="where to keep them (e.g. docs/reproductions/data/short/hig)")
    # not both: a sweep's report re-collects a cell that has runs, writing a plain results.csv
    # beside the packed one
    choice = parser.add_mutually_exclusive_group()
    choice.add_argument("--runs", action="store_true", help="also keep each run's files but its checkpoint")
    choice.add_argument("--gzip", action="store_true", help="keep results.csv gzipped (results.csv.gz)")
    args = parser.parse_args()
    copied = keep(args.source, args.target, args.runs, args.gzip)
    print(f"{len(copied)} files under {args.target}")


if __name__ == "__main__":
    main()

"""The committed short-study files (docs/reproductions/data/short) and the script that keeps
them: a clone redraws the reproduction reports from them alone."""

import importlib.util
import json
from pathlib import Path

import pytest

from physgrad.harness.calibration import read
from physgrad.harness.study import load_studies

ROOT = Path(__file__).resolve().parent.parent
KEPT = ROOT / "docs" / "reproductions" / "data" / "short"


def _keep_module():
    spec = importlib.util.spec_from_file_location("keep_studies", ROOT / "docs/reproductions/keep_studies.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _write(path: Path, text: str = "x"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_keep_copies_study_files_and_leaves_checkpoints_and_unfinished_studies(tmp_path):
    src, dst = tmp_path / "studies", tmp_path / "kept"
    done = src / "sweep" / "cell_a"
    for name in ("study.json", "summary.csv", "results.csv", "calibration.json"):
        _write(done / name)
    _write(done / "runs" / "adam-seed0" / "config.json")
    _write(done / "runs" / "adam-seed0" / "checkpoint" / "state.eqx")
    _write(src / "sweep" / "grid.json")
    _write(src / "running" / "study.json")  # no summary.csv: not finished

    keep = _keep_module().keep
    copied = {p.relative_to(dst).as_posix() for p in keep(src, dst)}
    assert copied == {
        "sweep/cell_a/study.json", "sweep/cell_a/summary.csv", "sweep/cell_a/results.csv",
        "sweep/cell_a/calibration.json", "sweep/grid.json",
    }  # fmt: skip
    assert not (dst / "running").exists()

    with_runs = {p.relative_to(tmp_path / "kept2").as_posix() for p in keep(src, tmp_path / "kept2", runs=True)}
    assert "sweep/cell_a/runs/adam-seed0/config.json" in with_runs
    assert not any("checkpoint" in p for p in with_runs)


def _kept_studies():
    return sorted(p.parent for p in KEPT.rglob("study.json") if "runs" not in p.relative_to(KEPT).parts)


@pytest.mark.parametrize("study", _kept_studies(), ids=lambda p: p.relative_to(KEPT).as_posix())
def test_each_kept_study_is_complete(study):
    """Every run the study planned is in its summary, with a curve in results.csv and a time
    per step in its calibration: the report draws its table and figure from these alone."""
    record = json.loads((study / "study.json").read_text())
    rows, results, order = load_studies(study.parent, [(study.name, "")])
    planned = {(m, str(s)) for m in record["methods"] for s in record["seeds"]}
    assert {(r["method"], r["seed"]) for r in rows} == planned
    assert all(r["status"] in ("finished", "diverged") for r in rows)
    curves = {(r["method"], r["seed"]) for r in results if r["split"] == "test"}
    assert curves == planned
    if "seconds" in record["budget"]:  # a calibrated budget: each method's step (each stage's) was timed
        calibration = read(study)
        assert calibration is not None and all(calibration.has(m) for m in order)

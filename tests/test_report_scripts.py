"""Every reproduction report script redraws from a clone, with nothing left to say "no results"
and no committed figure or file changed.

A fresh ``git clone`` of the checkout's HEAD holds only what is committed, as a reader's
clone would. Each script (``docs/reproductions/*_report.py`` and ``long/report.py``) runs
there with the clone's own ``src`` first on the path; the test fails when a script exits
non-zero, prints a section with no results (each script prints only the sections whose data
are kept, or points to the command that draws them), or leaves ``git status`` unclean: a
committed figure whose bytes change on a redraw (stale, or drawn non-deterministically) or
a file written that is not committed. The clone is reset after each script, so a failure
names its script. The slow tier (``make test-slow``): the five scripts together took about
nine minutes on one loaded core, most of it ``unrolling_report.py``'s coarse-solver baselines.

The fast tests check ``long/report.py``'s reading of the lanes that are still running, on
study directories built here: a lane that has evaluated nothing gets no section and no
figure, a KS lane is read in its own metric against ONE, and a tune lane's chosen runs
(``METHOD/final``) keep their method's calibrated step time beside the trial table.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REPRODUCTIONS = ROOT / "docs" / "reproductions"
SCRIPTS = sorted(p.relative_to(ROOT).as_posix() for p in REPRODUCTIONS.glob("*_report.py")) + [
    "docs/reproductions/long/report.py"
]


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout


@pytest.fixture(scope="module")
def clone(tmp_path_factory):
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs git and a git checkout")
    dest = tmp_path_factory.mktemp("report-clone") / "repo"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(dest)], check=True)
    return dest


def test_every_report_script_is_listed():
    assert len(SCRIPTS) == 5, SCRIPTS  # hig, sip, stable_bptt, unrolling and the long studies


@pytest.mark.slow
@pytest.mark.parametrize("script", SCRIPTS)
def test_report_script_redraws_from_a_clone_unchanged(clone, script):
    env = {**os.environ, "PYTHONPATH": str(clone / "src"), "MPLBACKEND": "Agg"}
    try:
        done = subprocess.run(
            [sys.executable, script], cwd=clone, env=env, capture_output=True, text=True, timeout=1800
        )
        output = done.stdout + done.stderr
        assert done.returncode == 0, f"{script} exited {done.returncode}:\n{output[-3000:]}"
        empty = [line for line in output.splitlines() if "no results" in line.lower()]
        assert not empty, f"{script} printed sections without kept data: {empty}"
        changed = _git(clone, "status", "--porcelain", "--untracked-files=all").splitlines()
        assert not changed, f"{script} changed the committed tree (stale or non-deterministic output): {changed}"
    finally:
        _git(clone, "checkout", "-q", "--", ".")
        _git(clone, "clean", "-qfdx")


# --- long/report.py on lanes still running (fast: study directories written here) ----------------
def _long_report(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("long_report", REPRODUCTIONS / "long" / "report.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    monkeypatch.setattr(module, "DATA", tmp_path / "data")
    monkeypatch.setattr(module, "FIGURES", tmp_path / "figures")
    (tmp_path / "figures").mkdir()
    return module


def _run(directory: Path, method: str, seed: int, metric: str, values: list[float], every: int, budget: int):
    """One run directory as physgrad writes it, enough for the report: config, metrics, summary."""
    run = directory / f"{method}-seed{seed}-0123456789"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"seed": seed, "method": method, "budget": {"steps": budget}}))
    rows = ["step,wall_time,split,metric,value"]
    rows += [f"{k * every},{k * 1.5:.6f},test,{metric},{v}" for k, v in enumerate(values)]
    (run / "metrics.csv").write_text("\n".join(rows) + "\n")
    steps = (len(values) - 1) * every
    (run / "summary.json").write_text(json.dumps({"status": "finished", "steps": steps, "diverged_step": None}))


def test_long_report_leaves_out_a_lane_with_nothing_evaluated(tmp_path, monkeypatch, capsys):
    report = _long_report(tmp_path, monkeypatch)
    (tmp_path / "data" / "just_started" / "wig").mkdir(parents=True)  # a lane's first run is compiling
    (tmp_path / "data" / "just_started" / "wig" / "study.json").write_text("{}")
    report.main([])
    out = capsys.readouterr().out
    assert "### just_started" not in out
    assert out.strip().endswith("just_started"), out  # the one line that names it
    assert not list((tmp_path / "figures").iterdir())


def test_long_report_reads_the_ks80_lane_in_rel_error_against_one(tmp_path, monkeypatch, capsys):
    report = _long_report(tmp_path, monkeypatch)
    study = tmp_path / "data" / "ks_correction_80ep_plateau"
    _run(study / "one" / "runs", "one", 0, "rel_error", [3.0, 2e-3, 1e-4], 2808, 5616)
    _run(study / "nog" / "runs", "nog", 0, "rel_error", [3.0, 1e-3, 5e-5], 2808, 5616)
    report.main(["ks_correction_80ep_plateau"])
    out = capsys.readouterr().out
    assert "final test rel_error" in out and "/ one" in out
    nog = next(line for line in out.splitlines() if line.startswith("| nog "))
    assert "| 0.5 |" in nog, nog  # 5e-5 / 1e-4
    assert (tmp_path / "figures" / "long_ks_correction_80ep_plateau.png").exists()


def test_long_report_reads_a_tune_lane(tmp_path, monkeypatch, capsys):
    report = _long_report(tmp_path, monkeypatch)
    study = tmp_path / "data" / "quantum_dipole_tuned_150s"
    tune = study / "adam"
    _run(tune / "final" / "runs", "adam", 0, "loss", [0.5, 1e-2, 1e-3], 103, 206)
    (tune / "tune.json").write_text(json.dumps({"problem": "quantum_dipole", "methods": ["adam"], "trials": 2,
                                                "defaults": {"adam": {"lr": 5e-4}}}))  # fmt: skip
    (tune / "trials.csv").write_text("method,trial,state,val_loss,steps,run_dir,params\n"
                                     'adam,0,COMPLETE,0.002,206,trials/adam/trial000,"{""lr"": 0.0005}"\n'
                                     'adam,1,COMPLETE,0.001,206,trials/adam/trial001,"{""lr"": 0.002}"\n')  # fmt: skip
    report.main([])
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| adam/final "))
    assert "| 0.1452 |" in row, row  # Adam's calibrated step (calibration.csv), not NaN
    assert "lr=0.002" in out  # the trial table: the chosen configuration
    assert (tmp_path / "figures" / "long_quantum_dipole_tuned_150s.png").exists()

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
"""

from __future__ import annotations

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

pytestmark = pytest.mark.slow


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

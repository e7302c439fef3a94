"""physgrad tune's Optuna storage: the journal file survives kill -9 (the tune resumes, its
finished trials kept), and a real PostgreSQL server (Debian's packages, started here) holds
the studies of ``--storage postgresql://...``."""

from __future__ import annotations

import csv
import glob
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from physgrad.harness.cli import main

ARGS = ["tune", "hig_toy", "--methods", "adam", "--trials", "3", "--seeds", "1", "--workers", "1",
        "--set", "batch_size=64", "--set", "eval_every=50"]  # fmt: skip


def _trials(storage, name="hig_toy:adam"):
    import optuna

    from physgrad.harness.tune import open_storage

    storage = open_storage(None, storage) if isinstance(storage, str) else storage
    return optuna.load_study(study_name=name, storage=storage).get_trials(deepcopy=False)


@pytest.mark.slow  # two tunes in a subprocess, one of them killed: ~1 minute
def test_the_journal_survives_kill_9_and_the_tune_resumes(tmp_path):
    from physgrad.harness.tune import open_storage

    out = tmp_path / "tune"
    command = [sys.executable, "-m", "physgrad", *ARGS, "--steps", "2000", "--out", str(out)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline, finished = time.monotonic() + 300, []
    try:
        while time.monotonic() < deadline and process.poll() is None:  # kill once trial 0 has finished
            if (out / "optuna.journal").exists():
                finished = [t for t in _trials(open_storage(out)) if t.state.name == "COMPLETE"]
                if finished and list((out / "trials").glob("*/trial001/metrics.csv")):
                    break
            time.sleep(0.2)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    assert finished, "trial 0 did not finish before the deadline"
    kept = {t.number: t.value for t in finished}
    assert main([*ARGS, "--steps", "2000", "--out", str(out)]) == 0  # the same command resumes
    trials = _trials(open_storage(out))
    assert sorted(t.number for t in trials) == [0, 1, 2] and {t.state.name for t in trials} == {"COMPLETE"}
    assert {t.number: t.value for t in trials if t.number in kept} == kept  # finished trials kept as they were
    with open(out / "trials.csv") as f:
        assert len(list(csv.DictReader(f))) == 3


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def postgres():
    """A PostgreSQL server from Debian's packages (``apt-get install postgresql``; .ci/run
    installs it), started in a temporary directory as the ``postgres`` user, trusting local
    connections; its URL. Skipped where the server or the driver is missing."""
    pytest.importorskip("psycopg2", reason="psycopg2 (physgrad[postgres]) is not installed")
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    if not found:
        pytest.skip("no PostgreSQL server (Debian: apt-get install postgresql)")
    bin_dir = os.path.dirname(found[-1])
    # under /tmp itself: pytest's own temporary tree is private to root
    root = Path(tempfile.mkdtemp(prefix="physgrad-pg-"))
    data, sockets = root / "data", root / "sock"
    sockets.mkdir()
    as_user: list[str] = []
    if os.geteuid() == 0:  # the server refuses to run as root: run it as the postgres user
        if shutil.which("runuser") is None:
            pytest.skip("running as root without runuser to start PostgreSQL as another user")
        try:
            shutil.chown(root, "postgres")
            shutil.chown(sockets, "postgres")
        except (LookupError, PermissionError) as e:
            pytest.skip(f"no postgres user to run the server as ({e})")
        as_user = ["runuser", "-u", "postgres", "--"]
    port = _free_port()
    run = lambda *cmd: subprocess.run([*as_user, *cmd], capture_output=True, text=True, timeout=120)  # noqa: E731
    done = run(f"{bin_dir}/initdb", "-D", str(data), "-A", "trust", "-U", "postgres")
    if done.returncode:
        pytest.skip(f"initdb failed: {done.stderr.strip()[-300:]}")
    done = run(f"{bin_dir}/pg_ctl", "-D", str(data), "-w", "-l", str(root / "log"), "-o",
               f"-p {port} -k {sockets} -c listen_addresses=''", "start")  # fmt: skip
    if done.returncode:
        pytest.skip(f"PostgreSQL did not start: {done.stderr.strip()[-300:]}")
    try:
        yield f"postgresql://postgres@/postgres?host={sockets}&port={port}"
    finally:
        run(f"{bin_dir}/pg_ctl", "-D", str(data), "-m", "immediate", "stop")
        shutil.rmtree(root, ignore_errors=True)


@pytest.mark.slow  # a PostgreSQL server and a tune: ~30 s
def test_postgresql_storage_holds_the_studies_and_a_second_run_resumes(postgres, tmp_path):
    command = [*ARGS, "--trials", "2", "--steps", "10", "--storage", postgres]
    assert main([*command, "--out", str(tmp_path / "a")]) == 0
    trials = _trials(postgres)
    assert [t.number for t in trials] == [0, 1] and {t.state.name for t in trials} == {"COMPLETE"}
    assert not (tmp_path / "a" / "optuna.journal").exists()  # the server holds them, not a journal
    assert main([*command, "--out", str(tmp_path / "a")]) == 0  # nothing asked again
    assert [t.number for t in _trials(postgres)] == [0, 1]

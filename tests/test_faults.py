"""Fault injection: run directories never lose or corrupt a result (issue 29).

Runs are killed with SIGKILL at named points (``PHYSGRAD_TEST_FAULT``, a test-only hook in
:mod:`physgrad.engine.rundir`) and at random moments, terminated with SIGTERM, written by two
processes at once, and given damaged checkpoints; a resumed run must end bit-identical to an
uninterrupted one (``params.eqx`` bytes, ``test_cases.json`` bytes, every metric value and
the summary apart from its timings), a refused one must say why in one line with exit 2.

The cheapest run there is: hig_toy with Adam, 20 steps at batch 64 on 64 test cases, a
checkpoint after every step (``checkpoint_seconds=0``), an evaluation every 5 steps. Subprocesses share XLA's
persistent compilation cache with the test session, so each costs about an interpreter start.
"""

import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import pytest

from physgrad.engine import rundir
from physgrad.harness.cli import main

STEPS = 20
# 64 test cases, not hig_toy's 1024: each process (every child here) writes test_cases.json by
# iterating the per-case losses, one compiled unstack per shape (~0.5 s of CPU at 1024).
ARGS = ["train", "hig_toy", "--method", "adam", "--set", "batch_size=64", "--set", "n_test=64",
        "--set", "checkpoint_seconds=0", "--set", "eval_every=5", "--quiet"]  # fmt: skip
TIMINGS = ("train_seconds", "compile_seconds", "time_per_step", "cpu_seconds", "cpu_steps", "cpu_time_per_step")


def with_extra(extra) -> list[str]:
    """ARGS with ``extra`` after them, an extra ``--set name=...`` replacing ARGS' own (a
    repeated --set key is refused)."""
    names = {extra[i + 1].partition("=")[0] for i in range(len(extra) - 1) if extra[i] == "--set"}
    base, i = [], 0
    while i < len(ARGS):
        if ARGS[i] == "--set" and ARGS[i + 1].partition("=")[0] in names:
            i += 2
            continue
        base.append(ARGS[i])
        i += 1
    return [*base, *extra]


def train(out, steps=STEPS, resume=False, extra=()):
    """The command line in this process; its exit status."""
    argv = [*with_extra(list(extra)), "--steps", str(steps), "--out", str(out)] + (["--resume"] if resume else [])
    return main(argv)


def spawn(out, steps=STEPS, resume=False, fault=None, extra=()) -> subprocess.Popen:
    """The command line in a child process (killable), with the test-only fault hook."""
    env = {**os.environ, rundir.FAULT_VARIABLE: fault or ""}
    # the child computes as this process does (tests/conftest.py turns x64 on; the command
    # line, like physgrad.fit, leaves JAX's setting to the user: here, the environment)
    env["JAX_ENABLE_X64"] = "1" if jax.config.jax_enable_x64 else "0"  # pyright: ignore[reportAttributeAccessIssue]
    cache = jax.config.jax_compilation_cache_dir  # the session's (tests/conftest.py), if any
    if cache:
        env["PHYSGRAD_COMPILATION_CACHE"] = cache
    argv = [*with_extra(list(extra)), "--steps", str(steps), "--out", str(out)] + (["--resume"] if resume else [])
    return subprocess.Popen([sys.executable, "-c", WITH_CTRL_C, *argv], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


# ``python -m physgrad`` with Ctrl-C raising KeyboardInterrupt, as in a terminal. A shell that
# starts the suite in the background (``make test &``, nohup) leaves SIGINT ignored; a child
# inherits that and Python keeps it ignored, so an ``int`` fault would do nothing.
WITH_CTRL_C = (
    "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "sys.argv[0] = 'physgrad'; runpy.run_module('physgrad', run_name='__main__', alter_sys=True)"
)


def result(run_dir: Path) -> dict:
    """What must not depend on interruptions: the final network's bytes, every test case's
    metrics, every logged value (not its wall time) and the summary without its timings."""
    summary = json.loads((run_dir / "summary.json").read_text())
    lines = (run_dir / "metrics.csv").read_text().splitlines()
    metrics = [(f[0], f[2], f[3], f[4]) for f in (line.split(",") for line in lines) if f[3] != "time_per_step"]
    return {
        "params": hashlib.sha256((run_dir / "params.eqx").read_bytes()).hexdigest(),
        "test_cases": (run_dir / "test_cases.json").read_text(),
        "metrics": metrics,
        "summary": {k: v for k, v in summary.items() if k not in TIMINGS},
    }


def snapshot(run_dir: Path) -> dict:
    """Every file's bytes and modification time."""
    return {str(p.relative_to(run_dir)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(run_dir.rglob("*")) if p.is_file()}  # fmt: skip


def manifest_step(run_dir: Path) -> int | None:
    try:
        return json.loads((run_dir / "checkpoint" / "manifest.json").read_text())["step"]
    except (OSError, ValueError, KeyError):
        return None


def wait_for_step(run_dir: Path, step: int, proc: subprocess.Popen, timeout: float = 120.0):
    deadline = time.monotonic() + timeout
    while manifest_step(run_dir) != step:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, f"no checkpoint at step {step}"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted run."""
    out = tmp_path_factory.mktemp("reference") / "run"
    assert train(out) == 0
    return out


@pytest.fixture
def copy_of(reference, tmp_path):
    def copy() -> Path:
        out = tmp_path / "run"
        shutil.copytree(reference, out)
        return out

    return copy


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("physgrad: error: "), err
    return err


# --- resuming is idempotent ----------------------------------------------------------------------
def test_a_met_budget_changes_nothing_and_a_smaller_one_is_refused(copy_of, capsys):
    out = copy_of()
    before = snapshot(out)
    assert train(out, resume=True) == 0
    assert "done already (finished)" in capsys.readouterr().out
    assert snapshot(out) == before
    assert train(out, steps=STEPS // 2, resume=True) == 2
    err = one_line_error(capsys)
    assert f"already trained {STEPS} steps" in err and f"{STEPS // 2} steps" in err
    assert snapshot(out) == before


def test_a_run_without_its_summary_finishes_from_the_final_checkpoint(reference, copy_of):
    """The files a kill after the final checkpoint leaves (the summary, params.eqx and
    test_cases.json are written after it); also a summary an older physgrad broke."""
    out = copy_of()
    for name in ("summary.json", "params.eqx", "test_cases.json"):
        (out / name).unlink()
    assert train(out, resume=True) == 0
    assert result(out) == result(reference)
    broken = json.loads((out / "summary.json").read_text()) | {"final_test_loss": None, "final_train_loss": None}
    (out / "summary.json").write_text(json.dumps(broken))
    assert not physgrad_is_complete(out)
    assert train(out, resume=True) == 0
    assert result(out) == result(reference)


def physgrad_is_complete(out):
    from physgrad.harness.train import is_complete

    return is_complete(out)


@pytest.mark.costly("the fast tier's one SIGKILL inside a checkpoint's commit: two child runs, each resumed")
def test_a_killed_run_resumes_bit_identical_from_named_points(reference, tmp_path):
    """SIGKILL between the final checkpoint and the summary, and between the two renames of
    a checkpoint's commit (only checkpoint.old/ is there); the killed writer's lock is
    released (the OS drops it), so the resume may write."""
    for fault in ("before-summary:kill", "checkpoint-aside:kill@12"):
        out = tmp_path / fault.split(":")[0]
        proc = spawn(out, fault=fault)
        proc.communicate(timeout=300)
        assert proc.returncode == -signal.SIGKILL, fault
        assert not (out / "summary.json").exists()
        if fault.startswith("checkpoint-aside"):
            assert not (out / "checkpoint").exists() and (out / "checkpoint.old").exists()
        assert train(out, resume=True) == 0, fault
        assert result(out) == result(reference), fault
        assert not (out / "checkpoint.old").exists() and not (out / "checkpoint.new").exists()
        assert not (out / rundir.LOCK_NAME).exists()  # the killed writer's lock was released


# --- SIGTERM, one writer --------------------------------------------------------------------------
# One child for both (each child starts and compiles again, ~4 s of CPU): while it holds still
# after step 7's checkpoint a second writer is refused, then SIGTERM stops it. That a SIGKILLed
# writer's lock is released (by the OS) is checked by the resumes after a SIGKILL above.
def test_a_second_writer_is_refused_and_sigterm_checkpoints_and_the_run_resumes_bit_identical(
    reference, tmp_path, capsys
):
    out = tmp_path / "run"
    proc = spawn(out, fault="step:sleep:120@7")  # holds still after step 7's checkpoint
    wait_for_step(out, 7, proc)
    for resume in (False, True):  # a second train on the same --out; --resume while it runs
        assert train(out, resume=resume) == 2
        err = one_line_error(capsys)
        assert "in use by another run" in err and f"pid {proc.pid}" in err and "train hig_toy" in err
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "terminated" in err, err
    assert json.loads((out / "summary.json").read_text())["status"] == "interrupted"
    assert manifest_step(out) == 7
    assert train(out, resume=True) == 0
    assert result(out) == result(reference)
    assert not (out / rundir.LOCK_NAME).exists()


def test_two_studies_on_one_directory(tmp_path, capsys):
    study = tmp_path / "study"
    with rundir.one_writer(study, "study"):
        argv = ["compare", "hig_toy", "--methods", "adam", "--steps", "2", "--out", str(study), "--quiet"]
        assert main(argv) == 2
        err = one_line_error(capsys)
        assert "in use by another study" in err and f"pid {os.getpid()}" in err


def test_a_refused_run_leaves_no_directory(tmp_path, capsys):
    """The lock makes the run directory first; a run refused after taking it (here: a batch
    that does not split over 3 devices) removes it again."""
    out = tmp_path / "new" / "run"
    assert train(out, extra=["--devices", "3"]) == 2
    assert "does not split over 3 devices" in one_line_error(capsys)
    assert not (tmp_path / "new").exists()


# --- damaged checkpoints ----------------------------------------------------------------------------
def _truncate(ckpt):
    data = (ckpt / "state.eqx").read_bytes()
    (ckpt / "state.eqx").write_bytes(data[: len(data) // 2])


def _flip(ckpt):
    data = bytearray((ckpt / "state.eqx").read_bytes())
    data[-9] ^= 0x04  # one bit of an array's data
    (ckpt / "state.eqx").write_bytes(bytes(data))


def _rewrite_counters(ckpt, counters: bytes):
    """New counters with a manifest that vouches for them (only the step disagrees)."""
    (ckpt / "counters.json").write_bytes(counters)
    manifest = json.loads((ckpt / "manifest.json").read_text())
    manifest["files"]["counters.json"] = {"bytes": len(counters), "sha256": hashlib.sha256(counters).hexdigest()}
    (ckpt / "manifest.json").write_text(json.dumps(manifest))


def _other_step(ckpt):
    counters = json.loads((ckpt / "counters.json").read_text())
    _rewrite_counters(ckpt, json.dumps({**counters, "step": counters["step"] - 1}).encode())


DAMAGE = {
    "truncated state": (_truncate, "state.eqx has"),
    "flipped bit": (_flip, "state.eqx does not match its checksum"),
    "missing state": (lambda c: (c / "state.eqx").unlink(), "state.eqx is missing"),
    "broken counters": (lambda c: (c / "counters.json").write_text('{"step": 2'), "counters.json has"),
    "broken manifest": (lambda c: (c / "manifest.json").write_text("{"), "manifest.json is not a valid manifest"),
    "mismatched step": (_other_step, "the manifest at step"),
    "empty": (lambda c: [p.unlink() for p in c.iterdir()], "neither manifest.json nor counters.json"),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_checkpoint_is_one_line(copy_of, capsys, damage):
    out = copy_of()
    (out / "summary.json").unlink()  # so the resume must read the checkpoint
    make, words = DAMAGE[damage]
    make(out / "checkpoint")
    before = snapshot(out)
    assert train(out, resume=True) == 2
    err = one_line_error(capsys)
    assert words in err and "is damaged" in err and "delete" in err, err
    assert snapshot(out) == before


def test_a_verified_checkpoint_of_another_structure_is_another_version(copy_of, tmp_path, capsys):
    """Checksums that verify over arrays that do not fit: 'another version of the method'."""
    other = tmp_path / "sgd"
    assert main(["train", "hig_toy", "--method", "sgd", "--set", "batch_size=64", "--steps", "2", "--quiet",
                 "--out", str(other)]) == 0  # fmt: skip
    out = copy_of()
    (out / "summary.json").unlink()
    state = (other / "checkpoint" / "state.eqx").read_bytes()
    (out / "checkpoint" / "state.eqx").write_bytes(state)
    manifest = json.loads((out / "checkpoint" / "manifest.json").read_text())
    manifest["files"]["state.eqx"] = {"bytes": len(state), "sha256": hashlib.sha256(state).hexdigest()}
    (out / "checkpoint" / "manifest.json").write_text(json.dumps(manifest))
    assert train(out, resume=True) == 2
    err = one_line_error(capsys)
    assert "written by another version of the method" in err and "damaged" not in err


def test_an_older_checkpoint_without_a_manifest_still_resumes(reference, copy_of):
    out = copy_of()
    for name in ("summary.json", "params.eqx", "test_cases.json", "checkpoint/manifest.json"):
        (out / name).unlink()
    assert train(out, resume=True) == 0
    assert result(out) == result(reference)


def test_a_torn_metrics_row_is_dropped_on_resume(reference, copy_of):
    """A kill during an append can cut metrics.csv's last line anywhere (here: '1' of '15')."""
    out = copy_of()
    rows = (out / "metrics.csv").read_bytes()
    keep = rows[: rows.index(b"\n15,") + 2]  # through step 10's rows, then a torn '1'
    (out / "metrics.csv").write_bytes(keep)
    shutil.rmtree(out / "checkpoint")
    for name in ("summary.json", "params.eqx", "test_cases.json"):
        (out / name).unlink()
    # resume from a checkpoint at step 10, as a run killed while appending step 15's rows
    tmp = out.parent / "ten"
    assert train(tmp, steps=10) == 0
    shutil.copytree(tmp / "checkpoint", out / "checkpoint")
    assert train(out, resume=True) == 0
    assert result(out) == result(reference)


# --- random kills (slow) -------------------------------------------------------------------------------
@pytest.mark.slow
def test_random_kills_never_change_the_result(tmp_path):
    """SIGKILL at random moments of a 200-step run (a checkpoint after every step, several
    commits a millisecond), resumed after each kill, over many trials: every run ends
    bit-identical to the uninterrupted one, whatever write a kill tore."""
    steps, extra = 200, ["--set", "eval_every=25"]
    reference = tmp_path / "reference"
    assert train(reference, steps=steps, extra=extra) == 0
    expected = result(reference)
    rng = random.Random(29)
    kills = 0
    for trial in range(12):
        out = tmp_path / f"trial{trial}"
        resume = False
        for attempt in range(6):
            previous = manifest_step(out)
            proc = spawn(out, steps=steps, resume=resume, extra=extra)
            start = time.monotonic()
            while manifest_step(out) == previous and proc.poll() is None:
                time.sleep(0.002)  # until training has begun (a new checkpoint) or the run ended
            if attempt < 4:
                time.sleep(rng.uniform(0.0, 1.5))
                if proc.poll() is None:
                    proc.kill()
                    kills += 1
            proc.communicate(timeout=300)
            assert proc.returncode in (0, -signal.SIGKILL), (trial, attempt, time.monotonic() - start)
            resume = True
            if proc.returncode == 0:
                break
        assert result(out) == expected, trial
    assert kills >= 12  # most trials were killed at least once

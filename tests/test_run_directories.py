"""Run directories, round two (issue 55): every interrupted run resumable, no write that can
destroy an old file, damaged inputs named in one line.

One test per probe of the issue (its number in the test's name where it has one). Each
fails on the physgrad before the fix: a traceback, a lost row, an emptied file, a
retrained run. The cheap runs of tests/test_faults.py (hig_toy, Adam, batch 64) are reused.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad.engine import rundir
from physgrad.harness.cli import main
from physgrad.harness.registry import METHODS, PROBLEMS
from test_faults import ARGS, STEPS, one_line_error, result, spawn, train


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted run of test_faults' cheapest configuration."""
    out = tmp_path_factory.mktemp("reference") / "run"
    assert train(out) == 0
    return out


def child(argv, *, fault="", limit_kib=None, env=None) -> subprocess.CompletedProcess:
    """The command line in a child process, with the fault hook and an optional limit on the
    size of a file it writes (``ulimit -f``, SIGXFSZ ignored: a write past it fails with
    EFBIG, as on a full disk). The limit is set by the shell, not by a fork of this process."""
    environment = {**os.environ, rundir.FAULT_VARIABLE: fault, **(env or {})}
    environment["JAX_ENABLE_X64"] = "1" if jax.config.jax_enable_x64 else "0"  # pyright: ignore[reportAttributeAccessIssue]
    cache = jax.config.jax_compilation_cache_dir
    if cache:
        environment["PHYSGRAD_COMPILATION_CACHE"] = cache
    command = [sys.executable, "-m", "physgrad", *argv]
    if limit_kib is not None:
        command = ["bash", "-c", f"trap '' XFSZ; ulimit -f {limit_kib}; exec \"$@\"", "bash", *command]
    return subprocess.run(command, env=environment, capture_output=True, text=True, timeout=300)


def one_line(text: str) -> str:
    text = text.strip()
    assert len(text.splitlines()) == 1 and "Traceback" not in text, text
    return text


# --- 1: toy2d ---------------------------------------------------------------------------------------
@pytest.mark.slow  # a few child processes: tens of seconds
def test_1_a_toy2d_run_resumes_after_sigterm_and_when_finished(tmp_path, capsys):
    args = ["train", "toy2d", "--method", "adam", "--set", "checkpoint_seconds=0", "--quiet"]
    reference = tmp_path / "reference"
    assert main([*args, "--steps", "40", "--out", str(reference)]) == 0
    out = tmp_path / "run"
    proc = child([*args, "--steps", "40", "--out", str(out)], fault="step:term@15")
    assert proc.returncode == 143, proc.stderr
    assert main([*args, "--steps", "40", "--out", str(out), "--resume"]) == 0
    assert (out / "params.eqx").read_bytes() == (reference / "params.eqx").read_bytes()
    capsys.readouterr()
    assert main([*args, "--steps", "40", "--out", str(out), "--resume"]) == 0
    assert "done already (finished)" in capsys.readouterr().out
    for _ in range(2):  # compare toy2d again: the run is found, not refused
        assert main(["compare", "toy2d", "--methods", "adam", "--steps", "20", "--out", str(tmp_path / "s"),
                     "--quiet"]) == 0  # fmt: skip
    assert "done already (finished), skipped" in capsys.readouterr().out


# --- 2: a signal during an evaluation ---------------------------------------------------------------
# In this process, not a child: the fault hook signals its own process (os.kill), so the run
# meets the same signal at the same point as in a child; here it also reuses the reference's
# compiled programs (a child started and compiled again: ~4 s of CPU each). Signals are
# delivered to the main thread, where pytest (and pytest-xdist's workers) run the tests.
@pytest.mark.parametrize("action, code", [("term", 143), ("int", 130)])
def test_2_a_signal_during_an_evaluation_loses_no_row(reference, tmp_path, monkeypatch, action, code):
    out = tmp_path / "run"
    monkeypatch.setenv(rundir.FAULT_VARIABLE, f"evaluating:{action}@3")  # as the evaluation at step 10 begins
    monkeypatch.setattr(rundir, "_passed", {})  # the hook's counts start afresh, as in a new process
    # Ctrl-C raises KeyboardInterrupt, as in a terminal (a suite started in the background
    # inherits SIGINT ignored; test_faults.WITH_CTRL_C does the same for its children)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        status = train(out)
    except KeyboardInterrupt as e:  # the command line let the signal escape: fail, do not end the session
        pytest.fail(f"the command line raised {type(e).__name__} instead of returning {code}")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert status == code
    monkeypatch.delenv(rundir.FAULT_VARIABLE)
    assert train(out, resume=True) == 0
    assert result(out) == result(reference)  # every metrics row, the network, the summary


# --- 3, 10: no write leaves a file empty -------------------------------------------------------------
def test_3_10_a_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "record.json"
    path.write_text("old")
    with pytest.raises(RuntimeError), rundir.atomic_file(path) as f:
        f.write(b"half of the new")
        raise RuntimeError("the disk filled up")
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["record.json"]


@pytest.mark.slow  # a few child processes: tens of seconds
def test_3_calibrate_out_keeps_the_old_record_when_its_write_fails(tmp_path):
    out = tmp_path / "c.json"
    # GN: the calibration saves the run's checkpoints (harness.run_chunks.Bookkeeping), and GN's on
    # hig_toy (its parameters alone, about 1 kB in float64) fit in 2 KiB, where the record does not
    argv = ["calibrate", "hig_toy", "--methods", "gn", "--repeats", "3", "--out", str(out)]
    assert child(argv).returncode == 0
    before = out.read_bytes()
    assert len(before) > 2048
    proc = child(argv, limit_kib=2)
    assert proc.returncode == 1 and "c.json" in one_line(proc.stderr)
    assert out.read_bytes() == before


@pytest.mark.slow  # a few child processes: tens of seconds
def test_10_report_keeps_its_files_when_a_write_fails(tmp_path):
    study = tmp_path / "s"
    assert main(["compare", "hig_toy", "--methods", "adam,sgd", "--steps", "20", "--seeds", "2", "--out", str(study),
                 "--set", "batch_size=64", "--quiet"]) == 0  # fmt: skip
    before = {p.name: p.read_bytes() for p in study.iterdir() if p.is_file()}
    proc = child(["report", str(study)], limit_kib=1)
    # a figure that cannot be written is a warning line (the tables stand), a table an error line
    assert proc.returncode in (0, 1), proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert "Traceback" not in proc.stderr and all(line.startswith("physgrad: ") for line in lines), proc.stderr
    assert "File too large" in proc.stderr
    assert {p.name: p.read_bytes() for p in study.iterdir() if p.is_file()} == before


# --- 4: a symbolic link as the lock ----------------------------------------------------------------
def test_4_a_lock_that_is_a_link_is_refused_and_its_target_untouched(tmp_path, capsys):
    out = tmp_path / "r"
    out.mkdir()
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    (out / ".lock").symlink_to(notes)
    assert train(out) == 2
    assert "symbolic link" in one_line_error(capsys)
    assert notes.read_text() == "mine"


# --- 5, 19: the dataset cache ------------------------------------------------------------------------
@pytest.mark.parametrize("damage", ["truncated", "empty", "flipped", "missing", "text"])
def test_5_a_damaged_cached_dataset_is_made_again(tmp_path, monkeypatch, capsys, damage):
    from physgrad.problems.sim.cache import cached_arrays

    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path))
    made = {"x": np.arange(1000.0), "y": np.ones((4, 5), np.float32)}
    cached_arrays("d", {"k": 1}, lambda: made)
    (path,) = tmp_path.glob("d-*.npz")
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "flipped":
        at = data.index(np.arange(1000.0).tobytes()[8:16])
        path.write_bytes(data[:at] + bytes([data[at] ^ 1]) + data[at + 1 :])
    elif damage == "missing":
        with np.load(path) as f:
            kept = {k: f[k] for k in f.files if k != "y"}
        np.savez(path, **kept)
    else:
        path.write_text("not a dataset")
    again = cached_arrays("d", {"k": 1}, lambda: made)
    assert all(np.array_equal(again[k], made[k]) for k in made)
    assert "is damaged" in one_line(capsys.readouterr().err)
    assert cached_arrays("d", {"k": 1}, lambda: 1 / 0)["x"].shape == (1000,)  # written again, whole
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_19_a_cache_that_is_a_file_is_one_line_before_generating(tmp_path, monkeypatch):
    from physgrad.problems.sim.cache import cached_arrays

    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "afile"))
    (tmp_path / "afile").write_text("")
    with pytest.raises(physgrad.ConfigError, match="names a file"):
        cached_arrays("d", {}, lambda: pytest.fail("generated before the check"))


# --- 6: non-finite data --------------------------------------------------------------------------
@pytest.mark.parametrize("split", ["train", "test"])
def test_6_non_finite_data_is_refused_as_data(split):
    class Broken(PROBLEMS["hig_toy"]):
        def make_data(self, key):
            data = super().make_data(key)
            data[split] = {**data[split], "x": data[split]["x"].at[7].set(jnp.nan)}
            return data

    with pytest.raises(physgrad.ConfigError, match=f"the '{split}' data hold a NaN or infinite value in sample 7"):
        physgrad.fit(Broken(), METHODS["adam"](), budget=physgrad.Budget(steps=3))


# --- 7, 16: identity, calibration ---------------------------------------------------------------
def test_7_two_studies_in_one_directory_keep_their_calibrations(tmp_path, capsys):
    base = ["compare", "hig_toy", "--methods", "adam", "--seconds", "0.05", "--out", str(tmp_path), "--quiet",
            "--set", "batch_size=64"]  # fmt: skip
    assert main(base) == 0
    assert main([*base, "--set", "lr=0.01"]) == 0
    capsys.readouterr()
    assert main(base) == 0
    out = capsys.readouterr().out
    assert "calibration: reusing" in out and "done already (finished), skipped" in out


def test_16_the_checkpoint_interval_is_not_part_of_the_identity(reference, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    assert train(out, resume=True, extra=["--set", "checkpoint_seconds=5"]) == 0
    assert "done already" in capsys.readouterr().out
    assert train(out, resume=True, extra=["--set", "lr=0.5"]) == 2
    assert "lr: 0.001 → 0.5" in one_line_error(capsys)  # the differing setting, old → new


# --- 8, 22: the memory guard --------------------------------------------------------------------------
def test_8_22_data_beyond_memory_is_refused_at_once(tmp_path, monkeypatch, capsys):
    from physgrad.engine import memory

    monkeypatch.setattr(memory, "available_bytes", lambda device=None: 2**20)
    argv = ["train", "exp_inverse", "--method", "hig", "--set", "n_train=200000", "--set", "batch_size=200000",
            "--steps", "1", "--out", str(tmp_path / "r")]  # fmt: skip
    assert main(argv) == 2
    err = one_line_error(capsys)
    assert "for the data and parameters alone" in err and "~0 B" not in err


# --- 9, 13, 14, 15, 22, 23, 24: the edge ------------------------------------------------------------
@pytest.mark.slow  # a few child processes: tens of seconds
def test_9_a_write_that_fails_mid_run_is_one_line_and_the_run_resumes(reference, tmp_path):
    out = tmp_path / "run"
    proc = child([*ARGS, "--steps", str(STEPS), "--out", str(out)], limit_kib=1)
    assert proc.returncode == 1, proc.stderr
    assert "File too large" in one_line(proc.stderr) and not (out / ".lock").exists()
    assert train(out, resume=True) == 0
    assert result(out) == result(reference)


@pytest.mark.slow  # a few child processes: tens of seconds
def test_13_sigterm_during_a_calibration_is_one_line_and_releases_the_lock(tmp_path):
    study = tmp_path / "s"
    argv = ["compare", "hig_toy", "--methods", "adam", "--seconds", "0.05", "--out", str(study), "--quiet"]
    proc = child(argv, fault="calibrating:term")
    assert proc.returncode == 143 and "terminated" in one_line(proc.stderr)
    assert not (study / ".lock").exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["train", "toy2d", "--method", "adam", "--out", "x" * 300], "255"),
        (["train", "toy2d", "--method", "adam", "--seed", str(2**63)], "2**63"),
        (["compare", "toy2d", "--methods", "adam", "--seeds", str(10**9)], "up to 10,000"),
        (["train", "toy2d", "--method", "adam", "--out", ""], "--out is empty"),
        (["compare", "toy2d", "--methods", "adam", "--set", "lr=1e-3,"], "empty value"),
        (["compare", "toy2d", "--methods", "adam", "--set", "lr=1e-3", "--set", "lr=1e-2"], "given twice"),
    ],
)
def test_14_15_23_24_bad_input_is_one_line(tmp_path, monkeypatch, capsys, argv, words):
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--steps", "2"]) == 2
    assert words in one_line_error(capsys)
    assert not any(tmp_path.iterdir())


def test_22_out_naming_a_file_reads_as_one_flag(tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    assert main(["train", "toy2d", "--method", "adam", "--steps", "2", "--out", str(tmp_path / "afile")]) == 2
    err = one_line_error(capsys)
    assert "--out '" in err and "----out" not in err


# --- 11, 12, 17: damaged or foreign directories ----------------------------------------------------
def test_11_a_damaged_run_file_names_the_file(tmp_path, capsys):
    study = tmp_path / "s"
    argv = ["compare", "hig_toy", "--methods", "adam", "--steps", "10", "--seeds", "2", "--out", str(study),
            "--set", "batch_size=64", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    run = sorted((study / "runs").iterdir())[0]
    (run / "config.json").write_text("{garbage")
    assert main(argv) == 2
    assert f"{run / 'config.json'} is damaged" in one_line_error(capsys)
    (run / "config.json").unlink()
    (study / "failures.json").write_text("[")
    assert main(argv) == 2
    assert "failures.json is damaged" in one_line_error(capsys)


def test_11_report_on_a_truncated_or_foreign_directory_is_one_line(tmp_path, capsys):
    study = tmp_path / "s"
    assert main(["compare", "hig_toy", "--methods", "adam", "--steps", "10", "--out", str(study),
                 "--set", "batch_size=64", "--quiet"]) == 0  # fmt: skip
    import gzip

    packed = gzip.compress((study / "summary.csv").read_bytes())
    (study / "summary.csv").unlink()
    (study / "summary.csv.gz").write_bytes(packed[: len(packed) // 2])
    capsys.readouterr()
    assert main(["report", str(study)]) == 2
    one_line_error(capsys)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "bench.json").write_text("[1, 2]")
    assert main(["report", str(foreign)]) == 2
    one_line_error(capsys)


def test_12_a_run_of_fit_resumed_from_the_command_line_is_one_line(tmp_path, capsys):
    out = tmp_path / "run"
    physgrad.fit(PROBLEMS["hig_toy"](), METHODS["adam"](), budget=physgrad.Budget(steps=3), out=out)
    assert main(["train", "hig_toy", "--method", "adam", "--steps", "3", "--out", str(out), "--resume"]) == 2
    assert "physgrad.fit" in one_line_error(capsys)


@pytest.mark.parametrize("holding", ["study.json", "summary.json"])
def test_17_train_into_a_directory_of_other_files_is_refused(tmp_path, capsys, holding):
    (tmp_path / holding).write_text('{"mine": 1}')
    assert main(["train", "toy2d", "--method", "adam", "--steps", "2", "--out", str(tmp_path)]) == 2
    assert "not a physgrad run" in one_line_error(capsys)
    assert (tmp_path / holding).read_text() == '{"mine": 1}'


# --- 18, 20, 21, 25: what a run directory keeps ---------------------------------------------------------
@pytest.mark.slow  # a few child processes: tens of seconds
def test_18_env_json_keeps_the_environment_that_started_the_run(reference, tmp_path):
    out = tmp_path / "run"
    proc = spawn(out, fault="step:term@10")
    proc.communicate(timeout=300)
    started = json.loads((out / "env.json").read_text())
    assert train(out, resume=True) == 0
    env = json.loads((out / "env.json").read_text())
    assert env["time"] == started["time"] and len(env["resumed"]) == 1


@pytest.mark.parametrize("deleted", [("params.eqx",), ("test_cases.json",), ("params.eqx", "test_cases.json")])
def test_20_21_a_finished_runs_deleted_files_are_made_again(reference, tmp_path, capsys, deleted):
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    for name in deleted:
        (out / name).unlink()
    assert train(out, resume=True) == 0
    assert "made again" in capsys.readouterr().out
    assert result(out) == result(reference)
    shutil.rmtree(out / "checkpoint")
    (out / deleted[0]).unlink()
    assert train(out, resume=True) == 2
    assert "no checkpoint" in one_line_error(capsys)


def test_25_a_diverged_summary_is_strict_json(tmp_path):
    out = tmp_path / "run"
    assert main(["train", "hig_toy", "--method", "sgd", "--steps", "20", "--set", "sgd.lr=1e12", "--set",
                 "batch_size=64", "--out", str(out), "--quiet"]) == 0  # fmt: skip

    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    summary = json.loads((out / "summary.json").read_text(), parse_constant=refuse)
    assert summary["status"] == "diverged"

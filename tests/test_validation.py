"""Inputs refused in one line before any work (issue 29): every setting and budget by type
and range at the edge (exit 2 on the command line), the Python API in the library's words."""

import dataclasses
import json
import math
import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import optax
import pytest

import physgrad
from physgrad import Budget, ConfigError, TrainSettings, checks
from physgrad.extras import MissingExtra
from physgrad.harness.cli import main
from physgrad.harness.config import make_config
from physgrad.harness.registry import METHODS, PROBLEMS, optax_names
from physgrad.harness.words import command_line_words
from physgrad.methods import Gradient, Method
from test_library import Cubic

ADAM = Method(Gradient(), optax.adam(1e-2))

# (arguments after `physgrad train hig_toy --method adam`, what the one line says)
TRAIN_PROBES = [
    (["--seconds", "nan"], "--seconds must be a finite number > 0, got nan"),
    (["--seconds", "inf"], "--seconds must be a finite number > 0, got inf"),
    (["--seconds", "-1"], "--seconds must be a finite number > 0"),
    (["--set", "lr=nan"], "setting 'lr' must be a finite number > 0, got nan"),
    (["--set", "lr=-1"], "setting 'lr' must be a finite number > 0, got -1.0"),
    (["--set", "eval_every=-1"], "setting 'eval_every' must be an integer >= 0, got -1"),
    (["--set", "eval_samples=-5"], "setting 'eval_samples' must be an integer >= 0, got -5"),
    (["--set", "eval_seconds=inf"], "setting 'eval_seconds' must be a finite number >= 0, got inf"),
    (["--set", "checkpoint_seconds=nan"], "setting 'checkpoint_seconds' must be a finite number >= 0"),
    (["--set", "hidden=-3"], "setting 'hidden' must be a positive integer, got -3"),
    (["--set", "n_train=0"], "setting 'n_train' must be a positive integer, got 0"),
    (["--set", "dtype=float17"], "setting 'dtype' must be one of float32, float64, got 'float17'"),
    (["--set", "batch_size=0"], "setting 'batch_size' must be a positive integer, got 0"),
    (["--set", "b1=1.5"], "setting 'b1' must be a number in [0, 1), got 1.5"),
    (["--set", "prdp_tau_stop=0"], "setting 'prdp_tau_stop' must be a number in (0, 1], got 0.0"),
]


def one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("physgrad: error: "), err
    return lines[0]


@pytest.mark.parametrize("args,says", TRAIN_PROBES)
def test_cli_refuses_a_bad_setting_or_budget_in_one_line(tmp_path, capsys, args, says):
    out = tmp_path / "run"
    budget = [] if args[0] == "--seconds" else ["--steps", "5"]
    assert main(["train", "hig_toy", "--method", "adam", *budget, *args, "--out", str(out)]) == 2
    assert says in one_line_error(capsys.readouterr().err)
    assert not out.exists()  # refused before anything was written (or generated)


def test_cli_refuses_an_out_that_is_a_file_or_cannot_be_made(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("not a run")
    for command in (["train", "hig_toy", "--method", "adam"], ["compare", "toy2d", "--methods", "gn"]):
        assert main([*command, "--steps", "2", "--out", str(a_file)]) == 2
        assert "is a file, not a directory; choose another --out" in one_line_error(capsys.readouterr().err)
        assert main([*command, "--steps", "2", "--out", str(a_file / "run")]) == 2
        line = one_line_error(capsys.readouterr().err)
        assert f"cannot be created: '{a_file}' is a file" in line
    assert a_file.read_text() == "not a run"


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_cli_refuses_an_out_that_cannot_be_written(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        assert main(["train", "hig_toy", "--method", "adam", "--steps", "2", "--out", str(locked / "run")]) == 2
        assert "is not writable; choose another --out" in one_line_error(capsys.readouterr().err)
    finally:
        locked.chmod(0o700)


# ``python -m physgrad`` once per argv of ``sys.argv[1]`` (JSON), in one interpreter: runpy runs
# physgrad/__main__.py as ``-m`` does and its SystemExit is the exit status. A separator line on
# stdout and on stderr after each ends that command's part (both stay the process's real files,
# so whatever a library writes there is seen too); the statuses are the last stdout line.
MODULE_ENTRY = """
import json, runpy, sys
codes = []
for argv in json.loads(sys.argv[1]):
    sys.argv = ["physgrad", *argv]
    try:
        runpy.run_module("physgrad", run_name="__main__", alter_sys=True)
        codes.append(0)
    except SystemExit as e:
        codes.append(e.code)
    print(SEPARATOR, flush=True)
    print(SEPARATOR, file=sys.stderr, flush=True)
print(json.dumps(codes))
"""
SEPARATOR = "---- end of one command ----"


def module_entry(probes: list[list[str]], **run) -> list[tuple[int, str, str]]:
    """(exit status, stdout, stderr) of ``python -m physgrad ARGV`` for each of ``probes``, run
    one after the other in one fresh interpreter (one start, ~3 s of CPU, instead of one each)."""
    script = f"SEPARATOR = {SEPARATOR!r}\n{MODULE_ENTRY}"
    done = subprocess.run([sys.executable, "-c", script, json.dumps(probes)], capture_output=True, text=True,
                          timeout=300, **run)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    *outs, last = done.stdout.split(SEPARATOR + "\n")
    errs = done.stderr.split(SEPARATOR + "\n")
    codes = json.loads(last)
    assert len(codes) == len(outs) == len(probes) and len(errs) == len(probes) + 1 and errs[-1] == "", done.stderr
    return list(zip(codes, outs, errs[:-1]))


def test_cli_in_a_fresh_process_exits_2_with_one_line(tmp_path):
    """The command line as a user runs it (``python -m physgrad``): exit status 2, one stderr
    line, no traceback, for a budget, a setting and an --out probe (one interpreter for the
    three)."""
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    train = ["train", "hig_toy", "--method", "adam"]
    probes = [[*train, "--seconds", "nan", "--out", str(tmp_path / "a")],
              [*train, "--steps", "2", "--set", "dtype=float17", "--out", str(tmp_path / "b")],
              [*train, "--steps", "2", "--out", str(a_file)]]  # fmt: skip
    says = ["--seconds must be a finite number > 0, got nan", "setting 'dtype' must be one of", "is a file"]
    for (code, _, err), words in zip(module_entry(probes), says, strict=True):
        assert code == 2 and words in one_line_error(err), err


def test_every_registered_default_passes_its_check():
    """The ranges hold for every problem's and method's own defaults (and the paper's)."""
    for problem in PROBLEMS:
        for method in [*METHODS, *optax_names()] if problem == "hig_toy" else METHODS:
            try:
                make_config(problem, method, budget=Budget(steps=1))
            except MissingExtra:
                pass


def test_checks_name_their_range():
    assert checks.check_setting("lr", 3, 1e-3) == 3.0 and isinstance(checks.check_setting("lr", 3, 1e-3), float)
    assert checks.check_setting("blocks", "kfac", "kfac") == "kfac"  # K-FAC's blocks is a string, HIG's an integer
    with pytest.raises(ConfigError, match=r"setting 'blocks' must be a positive integer, got 0"):
        checks.check_setting("blocks", 0, 8)
    with pytest.raises(ConfigError, match=r"setting 'cfl' must be a finite number, got nan"):
        checks.check_setting("cfl", math.nan, -0.75)  # unlisted floats: finite, any sign
    with pytest.raises(ConfigError, match=r"must be true or false, got 'yes'"):
        checks.check_setting("shuffle", "yes", False)
    with pytest.raises(ConfigError, match=r"must be an integer >= 0, got 1.5"):
        checks.check_setting("m", 1.5, 0)


# --- the Python API: its own arguments, in its own words -----------------------------------
@pytest.mark.unchecked("wrong amounts on purpose: Budget's own one-line error")
def test_budget_refuses_nan_infinite_and_fractional_amounts():
    for kind, amount in [("seconds", math.nan), ("seconds", math.inf), ("seconds", 0), ("steps", 2.5),
                         ("steps", 0), ("epochs", -1), ("steps", True)]:  # fmt: skip
        with pytest.raises(
            ConfigError, match=rf"Budget\({kind}=.*\): {kind} must be a (finite number > 0|positive integer)"
        ) as e:
            Budget(**{kind: amount})
        assert "--" not in str(e.value) and "--" in command_line_words(e.value)
    assert Budget(seconds=1).amount == 1 and Budget(steps=3).kind == "steps"


@pytest.mark.unchecked("wrong field values on purpose: TrainSettings' own one-line error")
def test_train_settings_refuse_out_of_range_fields():
    for field, value, says in [("eval_every", -1, "an integer >= 0"), ("eval_samples", -5, "an integer >= 0"),
                               ("checkpoint_seconds", math.nan, "a finite number >= 0"),
                               ("prdp_tau_step", 1.5, "a number in (0, 1]"), ("shuffle", "yes", "true or false")]:  # fmt: skip
        with pytest.raises(ConfigError, match=rf"TrainSettings field '{field}' must be {re.escape(says)}"):
            TrainSettings(**{field: value})
    assert TrainSettings(shuffle=None).shuffle is None


@pytest.mark.unchecked("wrong arguments on purpose: fit's own one-line errors")
def test_fit_refuses_bad_arguments_before_any_work(tmp_path):
    budget = Budget(steps=2)
    with pytest.raises(ConfigError, match=r"budget must be a physgrad.Budget, e.g. Budget\(steps=100\), got 100"):
        physgrad.fit(Cubic(), ADAM, budget=100, out=tmp_path / "a")  # pyright: ignore[reportArgumentType]
    with pytest.raises(ConfigError, match=r"batch_size must be a positive integer or None .*, got 0"):
        physgrad.fit(Cubic(), ADAM, budget=budget, out=tmp_path / "b", batch_size=0)
    with pytest.raises(ConfigError, match=r"settings must be a physgrad.TrainSettings"):
        physgrad.fit(Cubic(), ADAM, budget=budget, out=tmp_path / "c", settings={"eval_every": 1})  # pyright: ignore[reportArgumentType]
    with pytest.raises(ConfigError, match=r"Phase's batch_size must be a positive integer or None, got 0"):
        physgrad.Phase(ADAM, batch_size=0)
    with pytest.raises(ConfigError, match=r"Phase's steps must be a positive integer or None, got -3"):
        physgrad.Phase(ADAM, steps=-3)
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    with pytest.raises(ConfigError, match=r"out '.*a_file' is a file, not a directory; choose another out$") as e:
        physgrad.fit(Cubic(), ADAM, budget=budget, out=a_file)
    assert "--out" in command_line_words(e.value)  # the command line's words, only where it prints them
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]  # nothing was written


class VectorLoss(Cubic):
    def loss(self, y, sample):
        return (y - sample["y"]) ** 2  # one number per output component, not per sample


class EmptyTest(Cubic):
    def make_data(self, key):
        data = super().make_data(key)
        return {"train": data["train"], "test": jax.tree.map(lambda a: a[:0], data["test"])}


class NoTrain(Cubic):
    def make_data(self, key):
        return {"test": super().make_data(key)["test"]}


def test_a_loss_that_returns_a_vector_is_refused_naming_its_shape(tmp_path):
    with pytest.raises(ConfigError, match=r"loss\(y, sample\) must return a scalar for one sample, got shape \(2,\)"):
        physgrad.fit(VectorLoss(), ADAM, budget=Budget(steps=2), out=tmp_path / "a", batch_size=32)
    from physgrad.engine import scalar_loss

    assert scalar_loss(lambda y, s: jnp.sum(y))(jnp.ones(3), None) == 3.0


def test_empty_or_missing_splits_are_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"cubic: make_data's 'test' split is empty \(0 samples\)"):
        physgrad.fit(EmptyTest(), ADAM, budget=Budget(steps=2), out=tmp_path / "a", batch_size=32)
    with pytest.raises(ConfigError, match=r"cubic: make_data must return \{'train': samples, 'test': samples\}"):
        physgrad.fit(NoTrain(), ADAM, budget=Budget(steps=2), out=tmp_path / "b", batch_size=32)


def test_training_settings_are_defined_once():
    """TrainSettings defines the training settings; the command line's table and RunConfig's
    record (config.json, the settings flattened) follow it and must not drift."""
    from physgrad.harness.config import TRAIN_SETTINGS, RunConfig

    engine = {f.name for f in dataclasses.fields(TrainSettings)}
    assert set(TRAIN_SETTINGS) == engine | {"batch_size", "no_network"}
    record = RunConfig("p", "m", 0, Budget(steps=1), {}, ()).to_dict()  # config.json: the settings flattened
    recorded = set(record) - {"problem", "method", "seed", "budget", "problem_settings", "phases"}
    assert recorded == engine | {"no_network"}


@pytest.mark.parametrize(
    "problem,method,extra,says",
    [
        (
            "cartpole",
            "hig",
            [],
            "hig on cartpole: the Jacobian routes need predict(params, sample) to return one array",
        ),
        pytest.param(  # builds the Poisson data at the paper's grid: the slow tier
            "poisson",
            "khig",
            ["--no-network", "--set=n_train=16", "--set=n_test=4", "--set=batch_size=4"],
            "khig on poisson: khig: 16384 parameters are outside the dense layers it sees",
            marks=pytest.mark.slow,
        ),
    ],
)
def test_a_method_that_refuses_the_problem_in_the_memory_preflight_says_so_in_one_line(
    tmp_path, capsys, problem, method, extra, says
):
    """The memory guard's preflight computes footprints before the methods' checks; a
    method's refusal there (a closed loop's tuple of outputs for the Jacobian routes, KHIG's
    explicit-block limit: direct optimisation of a 128² field, no layer to factor) is the same
    one-line error, not a traceback."""
    argv = ["train", problem, "--method", method, "--steps", "1", "--out", str(tmp_path / "run"), *extra]
    assert main(argv) == 2
    assert says in one_line_error(capsys.readouterr().err)

"""The engine package: the command line and physgrad.fit run one computation, the memory
guard's preflight skips only what it must (and lets a bug surface), the abstract setup is
the concrete one's shapes, and the library's errors speak the library's words."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import optax
import pytest

import physgrad
from physgrad import Budget, ConfigError, engine
from physgrad.engine import Phase, abstract_setup, build_setup, preflight
from physgrad.harness.words import command_line_words
from physgrad.methods import AbstractRule, Gradient, Method
from physgrad.nets import parameter_count
from test_library import Cubic

ADAM = Method(Gradient(), optax.adam(1e-2))
RUN = {"problem": "hig_toy", "method": "adam:3,hig", "steps": 6, "seed": 3}  # x64 on globally would change its numbers


def fresh(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    """``python args`` in a fresh interpreter with JAX's defaults (x64 off), as a user runs it."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PHYSGRAD_CACHE"] = str(tmp_path / "cache")
    done = subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-4000:]
    return done


def metric_rows(run_dir: Path) -> list[tuple[str, str, str, str]]:
    """metrics.csv without its timings (wall time, time per step): step, split, metric, value."""
    with (run_dir / "metrics.csv").open() as f:
        return [
            (r["step"], r["split"], r["metric"], r["value"])
            for r in csv.DictReader(f)
            if r["metric"] != "time_per_step"
        ]


@pytest.mark.slow  # two fresh interpreters, each importing physgrad and training (~18 s)
def test_the_command_line_and_fit_run_the_same_computation(tmp_path):
    """One configuration (Adam for 3 steps, then HIG, on hig_toy: HIG's Gram route computes in
    scoped float64; Adam's final network differs when x64 is on globally, so a CLI that turned it
    on would differ here) run by
    ``python -m physgrad train`` and by ``physgrad.fit`` in fresh interpreters: the same
    final network bit for bit and the same metrics; neither leaves x64 on for the run."""
    cli, lib = tmp_path / "cli", tmp_path / "fit"
    fresh(["-m", "physgrad", "train", RUN["problem"], "--method", RUN["method"], "--steps", str(RUN["steps"]),
           "--seed", str(RUN["seed"]), "--set", "eval_every=2", "--out", str(cli), "--quiet"], tmp_path)  # fmt: skip
    code = f"""
        import physgrad
        from physgrad.harness.config import make_config
        from physgrad.harness.train import phases_of, problem_of, settings_of

        config = make_config({RUN["problem"]!r}, {RUN["method"]!r}, budget=physgrad.Budget(steps={RUN["steps"]}),
                             seed={RUN["seed"]}, settings={{"eval_every": "2"}})
        physgrad.fit(problem_of(config), phases_of(config), budget=config.budget, out={str(lib)!r}, seed=config.seed,
                     settings=settings_of(config))
    """
    fresh(["-c", textwrap.dedent(code)], tmp_path)
    for run in (cli, lib):
        assert json.loads((run / "env.json").read_text())["x64"] is False
    assert (cli / "params.eqx").read_bytes() == (lib / "params.eqx").read_bytes()
    assert metric_rows(cli) == metric_rows(lib) and len(metric_rows(cli)) > 6
    a, b = (json.loads((run / "summary.json").read_text()) for run in (cli, lib))
    for key in ("status", "steps", "final_train_loss", "final_test_loss", "best_test_loss", "step_stat_totals"):
        assert a[key] == b[key], key


# --- the memory guard's preflight --------------------------------------------------------------
class NumpyData(Cubic):
    """Data made by host code (as a dataset read from disk): not traceable abstractly."""

    def make_data(self, key):
        x = np.random.default_rng(np.asarray(jax.random.key_data(key))).uniform(-1, 1, (2 * self.n, 2))
        data = {"x": x.astype(np.float32), "y": (x + 0.1 * x**3).astype(np.float32)}
        return {"train": {k: v[: self.n] for k, v in data.items()}, "test": {k: v[self.n :] for k, v in data.items()}}


class BrokenFootprint(AbstractRule):
    """The gradient, with a bug in its footprint (not a missing concrete value)."""

    def __call__(self, objective, params, batch):
        return Gradient()(objective, params, batch)

    def footprint(self, objective, params, batch, devices=1):
        raise KeyError("a bug in the footprint")


def test_preflight_skips_host_data_and_refused_settings_but_a_bug_surfaces():
    preflight(NumpyData(), [Phase(ADAM, None, 32)], seed=0)  # checked once the data exist
    preflight(Cubic(), [Phase(ADAM, None, 4096)], seed=0)  # build_setup refuses the batch size, in its order
    with pytest.raises(ConfigError, match="batch_size 4096 exceeds the 256 training samples"):
        build_setup(Cubic(), [Phase(ADAM, None, 4096)], seed=0)
    broken = Method(BrokenFootprint(), optax.adam(1e-2))
    with pytest.raises(KeyError, match="a bug in the footprint"):
        preflight(Cubic(), [Phase(broken, None, 32)], seed=0)


def test_a_host_data_problem_trains_with_the_guard_on(tmp_path):
    summary = physgrad.fit(NumpyData(), ADAM, budget=Budget(steps=3), out=tmp_path / "run", batch_size=32)
    assert summary["status"] == "finished" and summary["steps"] == 3


def test_the_abstract_setup_has_the_shapes_of_the_built_one():
    """The shapes the memory preflight and the bench's applicability check see."""
    built = build_setup(Cubic(), [Phase(ADAM, None, 32)], seed=0)
    shapes = abstract_setup(Cubic())
    assert shapes.n_train == 256 and shapes.parameter_count == parameter_count(built.params)
    same = jax.tree.map(lambda a, s: (a.shape, a.dtype) == (s.shape, s.dtype), built.params, shapes.params)
    assert all(jax.tree.leaves(same))
    assert abstract_setup(NumpyData()).n_train is None  # host data: the network from make_network


# --- errors in the library's words -------------------------------------------------------------
@pytest.mark.unchecked("wrong fit arguments on purpose: fit's own one-line errors")
def test_fit_errors_name_fit_arguments_and_carry_the_flags_line(tmp_path):
    physgrad.fit(Cubic(), ADAM, budget=Budget(steps=2), out=tmp_path / "run", batch_size=32)
    with pytest.raises(ConfigError) as exists:
        physgrad.fit(Cubic(), ADAM, budget=Budget(steps=2), out=tmp_path / "run", batch_size=32)
    assert "resume=True" in str(exists.value) and "--" not in str(exists.value)
    assert "--resume" in command_line_words(exists.value) and "--out" in command_line_words(exists.value)
    with pytest.raises(ConfigError) as past:
        physgrad.fit(Cubic(), ADAM, budget=Budget(steps=1), out=tmp_path / "run", batch_size=32, resume=True)
    assert "more than the budget of 1 steps" in str(past.value) and "--" not in str(past.value)
    assert "choose another --out" in command_line_words(past.value)
    with pytest.raises(ConfigError) as devices:
        physgrad.fit(Cubic(), ADAM, budget=Budget(steps=2), out=tmp_path / "d", devices="many")
    assert "devices must be" in str(devices.value) and "--devices" in command_line_words(devices.value)


def test_the_package_keeps_the_engine_names_and_modules_stay_small():
    for name in ("fit", "Budget", "Phase", "TrainSettings", "TrainState", "build_setup", "make_step", "make_evaluate",
                 "Placement", "Steps", "grouped_order", "read_metrics", "read_summary", "is_complete", "environment",
                 "scalar_loss", "initial_network", "ADDED_SETTINGS", "UNGUARDED_SETTINGS", "_identity"):  # fmt: skip
        assert hasattr(engine, name), name
    for module in Path(engine.__file__).parent.glob("*.py"):
        assert len(module.read_text().splitlines()) <= 500, module.name

"""physgrad tune: the declared search spaces, the validation split, trials on a tiny problem
(library and command line), successive halving and the report (harness/tune.py, spaces.py,
tune_report.py, engine/splits.py)."""

from __future__ import annotations

import csv
import json
import math

import jax
import numpy as np
import pytest

import physgrad
from physgrad import Budget
from physgrad.engine.splits import HoldOut, TestSplit, held_out_count
from physgrad.errors import ConfigError
from physgrad.harness import spaces
from physgrad.harness.cli import main
from physgrad.harness.registry import METHODS, PROBLEMS, hyperparameters
from physgrad.harness.tune import NoPruning, SuccessiveHalving


def test_every_registered_method_has_a_space_resolved_against_its_defaults():
    for method in METHODS:
        defaults = hyperparameters(method)
        found = spaces.distributions(method, defaults)
        assert "lr" in found or method in ("kfac", "kfac_hig"), method  # every method searches its learning rate
        for name, d in found.items():
            assert d.log and 0 < d.low < d.high, (method, name)
    lr = spaces.distributions("adam", {"lr": 1e-3})["lr"]
    assert (lr.low, lr.high) == pytest.approx((1e-5, 1e-1))  # two decades either side of the default
    assert set(spaces.distributions("hig", hyperparameters("hig"))) == {"lr", "truncation"}
    assert set(spaces.distributions("sip", hyperparameters("sip"))) == {"lr", "eta"}
    assert set(spaces.distributions("bptt", hyperparameters("bptt"))) == {"lr", "clip_threshold"}
    # K-FAC's adaptive step sets its own rate: lr is searched only without it
    assert set(spaces.distributions("kfac", hyperparameters("kfac"))) == {"damping"}
    assert set(spaces.distributions("kfac", {**hyperparameters("kfac"), "adaptive": False})) == {"lr", "damping"}
    assert set(spaces.distributions("optax:lion", {"lr": 1e-3})) == {"lr"}


def test_a_space_naming_no_hyperparameter_or_a_sequence_is_refused_in_one_line():
    with pytest.raises(ConfigError, match="no hyperparameter 'beta'.*valid choices: lr"):
        spaces.distributions("adam", {"lr": 1e-3}, {"adam": {"beta": spaces.LogUniform(0.1, 1.0)}})
    with pytest.raises(ConfigError, match="single methods"):
        spaces.space_of("adam:10,hig")
    with pytest.raises(ConfigError, match="0 < low < high"):
        spaces.LogUniform(1.0, 0.1)


def test_holdout_holds_out_the_end_of_train_or_takes_the_val_split_and_drops_test():
    problem = PROBLEMS["hig_toy"]()
    data = problem.make_data(jax.random.key(0))
    held = HoldOut(0.25)(data)
    n = jax.tree.leaves(data["train"])[0].shape[0]
    k = held_out_count(n, 0.25)
    train, test = jax.tree.leaves(held["train"])[0], jax.tree.leaves(held["test"])[0]
    assert train.shape[0] == n - k and test.shape[0] == k and "val" not in held
    np.testing.assert_array_equal(np.asarray(test), np.asarray(jax.tree.leaves(data["train"])[0][n - k :]))
    np.testing.assert_array_equal(np.asarray(train), np.asarray(jax.tree.leaves(data["train"])[0][: n - k]))
    assert TestSplit()(data) is data

    own = HoldOut()({**data, "val": data["train"]})
    assert own["test"] is own["val"] is data["train"] and own["train"] is data["train"]  # the problem's own val
    with pytest.raises(ValueError, match="fraction"):
        held_out_count(10, 1.5)
    with pytest.raises(ValueError, match="fraction"):
        HoldOut(1.5)


def test_a_holdout_run_never_evaluates_or_trains_on_test(tmp_path):
    """fit with split=HoldOut on the user's own problem object: its test split (here made
    huge, so any use of it shows) reaches neither the training nor the evaluation; the
    run's "test" loss is the held-out end of train, and every fresh draw is split too."""
    import jax.numpy as jnp
    import optax

    from physgrad.engine import setup as engine_setup
    from physgrad.methods import Gradient

    class PoisonedTest(type(PROBLEMS["hig_toy"]())):
        def make_data(self, key):
            out = super().make_data(key)
            return {**out, "test": jax.tree.map(lambda a: a * 1e6, out["test"])}

    problem = PoisonedTest()
    method = physgrad.Method(Gradient(), optax.adam(1e-2))
    settings = physgrad.TrainSettings(fresh_samples=True, eval_every=2)
    result = physgrad.fit(problem, method, budget=Budget(steps=4), batch_size=64, seed=3, settings=settings,
                          split=HoldOut(0.25), out=tmp_path / "run")  # fmt: skip
    data = engine_setup.run_data(problem, HoldOut(0.25), jax.random.fold_in(jax.random.key(3), 0))
    held = data["test"]
    losses = jax.vmap(lambda s: problem.loss(problem.predict(result.network, s), s))(held)
    assert result.summary["final_test_loss"] == pytest.approx(float(jnp.mean(losses)), rel=1e-5)
    assert result.summary["final_test_loss"] < 1e3  # the poisoned test split would give ~1e12
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["validation"] == HoldOut(0.25).note and config["problem"].endswith(
        "PoisonedTest()"
    )  # the problem itself
    # a fresh draw keeps the held-out fraction's size: the compiled step is reused on it
    fresh = engine_setup.run_data(problem, HoldOut(0.25), jax.random.key(9), check=False)["train"]
    assert jax.tree.leaves(fresh)[0].shape == jax.tree.leaves(data["train"])[0].shape


def test_a_holdout_records_what_older_tuning_trials_recorded():
    """A trial's record keeps the words the older Validation wrapper wrote (committed tuning
    studies' config.json), so those records read, and compare, as the same runs."""
    older = ("test split = the problem's val split, or else the last 0.2 of train (held out, not trained on); "
             "the real test split is never built")  # fmt: skip
    assert HoldOut(0.2).note == older and TestSplit().note is None


def test_a_direct_optimisation_problem_is_validated_on_its_objective():
    """toy2d optimises its one sample directly (the same split object is train and test):
    there is nothing unseen to hold out, so a trial's validation data is that sample and
    its trials finish (a hold-out of one sample would be refused)."""
    from physgrad.engine import abstract_data
    from physgrad.precision import float64_scope

    with float64_scope(True):
        held = HoldOut(0.2)(PROBLEMS["toy2d"]().make_data(jax.random.key(0)))
        shapes = abstract_data(PROBLEMS["toy2d"](), 0, HoldOut(0.2))  # traced whole: train is still test
    assert held["train"] is held["test"]
    assert shapes is not None and jax.tree.leaves(shapes["test"])[0].shape[0] == 1
    with pytest.raises(ValueError, match="cannot hold out"):
        held_out_count(1, 0.2)


def test_prdp_refines_the_solver_of_the_problem_a_trial_trains():
    """A tuning trial's problem is the problem itself (the split is the run's), so PRDP reads
    and refines its iteration count."""
    from physgrad.engine import TrainSettings
    from physgrad.engine.strategies import Fidelity

    problem = PROBLEMS["advection_1d"](iterations=12)
    fidelity = Fidelity.of(problem, TrainSettings(prdp=True, prdp_start=3))
    assert (fidelity.name, fidelity.full) == ("iterations", 12)
    assert problem.with_refined(3).iterations == 3 and problem.iterations == 12


def test_successive_halving_rungs():
    assert SuccessiveHalving(3, 3).rungs(90) == [10, 30, 90]
    assert SuccessiveHalving(2, 2).rungs(40) == [20, 40]
    assert NoPruning().rungs(40) == [40]
    with pytest.raises(ConfigError):
        SuccessiveHalving(1, 2)


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_tune_a_problem_object_two_trials_per_method(tmp_path):
    """physgrad.tune on a user's problem object: trial 0 is the untuned configuration, the
    other a QMC point of the space; the chosen one is re-run and reported on test."""
    problem = PROBLEMS["hig_toy"]()
    result = physgrad.tune(problem, ["hig"], trials=2, budget=Budget(steps=10), out=tmp_path, seeds=1,
                           settings={"batch_size": 64, "eval_every": 10}, echo=lambda line: None)  # fmt: skip
    trials = _rows(tmp_path / "trials.csv")
    assert [(r["method"], r["trial"]) for r in trials] == [("hig", "0"), ("hig", "1")]
    assert json.loads(trials[0]["params"]) == {"lr": 1.0, "truncation": 1e-6}  # the untuned defaults first
    info = json.loads((tmp_path / "tune.json").read_text())
    for r in trials:
        for name, value in json.loads(r["params"]).items():
            low, high = info["bounds"][r["method"]][name]
            assert low <= value <= high
    for method, params in result.best.items():
        done = [r for r in trials if r["method"] == method and r["state"] == "COMPLETE"]
        best = min(done, key=lambda r: float(r["val_loss"]))
        assert params == json.loads(best["params"])
    assert [(r["method"], r["seed"]) for r in result.final] == [("hig", 0)]
    assert all(math.isfinite(r["final_test_loss"]) for r in result.final)
    config = json.loads((tmp_path / "trials" / "hig" / "trial000" / "config.json").read_text())
    assert "never built" in config["validation"]  # the trial's test split is the held-out part of train
    with pytest.raises(ConfigError, match="steps or epochs"):
        physgrad.tune(problem, ["adam"], budget=Budget(seconds=1.0), out=tmp_path / "s", echo=lambda line: None)


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    """``physgrad tune hig_toy`` from the command line, 2 trials per method, in this process."""
    out = tmp_path_factory.mktemp("tune")
    code = main(["tune", "hig_toy", "--methods", "adam,hig", "--trials", "2", "--steps", "12", "--seeds", "1",
                 "--workers", "1", "--set", "eval_every=6", "--set", "batch_size=64", "--out", str(out)])  # fmt: skip
    assert code == 0
    return out


def test_tune_from_the_command_line_writes_trials_best_and_a_final_study(tuned):
    trials = _rows(tuned / "trials.csv")
    assert len(trials) == 4 and {r["state"] for r in trials} == {"COMPLETE"}
    assert (tuned / "optuna.journal").exists() and (tuned / "best.json").exists()
    assert (tuned / "final" / "summary.csv").exists() and len(_rows(tuned / "final" / "summary.csv")) == 2
    best = json.loads((tuned / "best.json").read_text())
    study = json.loads((tuned / "final" / "study.json").read_text())
    assert study["settings"]["hig.lr"] == best["hig"]["lr"]  # the chosen configuration is what ran on test


def test_tune_again_keeps_its_trials_and_report_redraws_it(tuned, capsys):
    before = (tuned / "trials.csv").read_text()
    assert main(["tune", "hig_toy", "--methods", "adam,hig", "--trials", "2", "--steps", "12", "--seeds", "1",
                 "--workers", "1", "--set", "eval_every=6", "--set", "batch_size=64", "--out", str(tuned)]) == 0  # fmt: skip
    assert (tuned / "trials.csv").read_text() == before  # nothing asked or run again
    (tuned / "trials.png").unlink()
    assert main(["report", str(tuned)]) == 0
    out = capsys.readouterr().out
    assert "untuned val loss" in out.replace("\n", " ") or "untuned" in out
    assert (tuned / "trials.png").exists()


@pytest.mark.slow  # ~6 s of CPU: a seconds budget calibrates a real step first
def test_a_method_whose_step_cannot_be_built_is_left_out_and_the_others_are_tuned(tmp_path, monkeypatch):
    """A seconds budget calibrates first; where one method's step cannot be built (here a
    RuntimeError from its build), the tuning says so in one line and tunes the rest,
    as a bench over many methods must."""
    from physgrad.harness import calibration

    real = calibration.step_programs

    def building(config, *args, **kwargs):
        if config.method == "gn":
            raise RuntimeError("no step for you")
        return real(config, *args, **kwargs)

    monkeypatch.setattr(calibration, "step_programs", building)
    main_args = ["tune", "hig_toy", "--methods", "adam,gn", "--trials", "1", "--seconds", "0.05", "--seeds", "1",
                 "--workers", "1", "--set", "batch_size=64", "--out", str(tmp_path), "--quiet"]  # fmt: skip
    assert main(main_args) == 0
    assert [r["method"] for r in _rows(tmp_path / "trials.csv")] == ["adam"]
    assert json.loads((tmp_path / "tune.json").read_text())["methods"] == ["adam"]


def test_tune_refuses_bad_input_in_one_line(tmp_path, capsys):
    assert main(["tune", "nope", "--steps", "5", "--out", str(tmp_path / "a")]) == 2
    assert main(["tune", "hig_toy", "--methods", "adam", "--trials", "0", "--steps", "5"]) == 2
    assert main(["tune", "hig_toy", "--methods", "adam", "--seconds", "1", "--no-calibrate"]) == 2
    err = capsys.readouterr().err
    assert "unknown problem 'nope'" in err and "--trials" in err and "calibrated" in err


@pytest.mark.slow  # two tunes of 3 trials: ~30 s
def test_successive_halving_prunes_and_resumes_the_survivors(tmp_path):
    """With η = 2 and two rungs, of trials 1-2 the worse stops at half the steps (PRUNED,
    its rung's loss recorded) and the better one resumes from its run to the full budget:
    its validation loss is the one an uninterrupted run reaches."""
    problem = PROBLEMS["hig_toy"]()
    settings = {"batch_size": 64, "eval_every": 6}
    result = physgrad.tune(problem, ["adam"], trials=3, budget=Budget(steps=12), out=tmp_path / "sh", seeds=1,
                           settings=settings, pruning=SuccessiveHalving(2, 2), echo=lambda line: None)  # fmt: skip
    states = {r["trial"]: r["state"] for r in result.trials}
    assert states[0] == "COMPLETE" and sorted([states[1], states[2]]) == ["COMPLETE", "PRUNED"]
    survivor = next(t for t in (1, 2) if states[t] == "COMPLETE")
    plain = physgrad.tune(problem, ["adam"], trials=3, budget=Budget(steps=12), out=tmp_path / "plain", seeds=1,
                          settings=settings, echo=lambda line: None)  # fmt: skip
    value = {r["trial"]: r["val_loss"] for r in plain.trials}
    assert next(r["val_loss"] for r in result.trials if r["trial"] == survivor) == value[survivor]

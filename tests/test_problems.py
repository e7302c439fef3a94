"""Every registered problem honours the contract; the HIG toy's loss against NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad import Budget
from physgrad.config import make_config, phase_methods
from physgrad.problems import HigToy
from physgrad.registry import METHODS, PROBLEMS
from physgrad.train import build

# The time-stepper problems generate their data; these keep it to seconds (the paper sizes
# are exercised by the reproduction runs, not by the tests).
SMALL_DATA = {
    "ks": {"frames": "40", "warmup_frames": "20", "n_ics": "1", "n_test": "1", "long_horizon": "12",
           "dataset_fraction": "1.0"},
    "kolmogorov": {"n": "16", "refinement": "2", "forcing_mode": "4", "frames": "10", "warmup_frames": "10",
                   "n_test": "1", "long_horizon": "12"},
    "advection_1d": {"n_train": "4", "n_test": "2", "horizon": "16"},
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_registered_problem_contract(name, tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path))
    cls = PROBLEMS[name]
    assert cls.name == name and cls.description and cls.source and cls.__doc__
    for method in cls.default_methods:
        assert set(phase_methods(method)) <= set(METHODS)
    small = SMALL_DATA.get(name) or {k: "32" for k in ("n_train", "n_test") if k in cls.settings()}
    b = str(min(8, cls.default_batch_size))  # toy2d optimises one x
    setup = build(make_config(name, "hig", budget=Budget(steps=1), settings={**small, "batch_size": b}))
    batch = jax.tree.map(lambda a: a[: int(b)], setup.data["train"])
    losses = setup.objective.sample_losses(setup.params, batch)
    assert losses.shape == (int(b),) and bool(jnp.all(jnp.isfinite(losses)))
    sample = jax.tree.map(lambda a: a[0], batch)
    if setup.objective.target is not None:  # SIP's y-space target has the simulator's shape
        y = setup.objective.predict(setup.params, sample)
        assert setup.objective.target(sample).shape == y.shape
        assert float(setup.objective.loss(setup.objective.target(sample), sample)) == 0.0
    # the same seed gives the same data and network
    again = build(make_config(name, "hig", budget=Budget(steps=1), settings={**small, "batch_size": b}))
    for a, b in zip(jax.tree.leaves((setup.data, setup.params)), jax.tree.leaves((again.data, again.params))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("lam", [1.0, 0.01])
def test_hig_toy_loss_against_numpy(lam):
    problem = HigToy(lam=lam, dtype="float64")
    x, y = 0.37, np.array([0.2, -1.3])
    want = 0.5 * (y[0] - np.sin(6 * x)) ** 2 + 0.5 * (lam * y[1] - np.cos(9 * x)) ** 2
    got = problem.loss(problem.simulate(jnp.asarray(y), {"x": jnp.asarray([x])}), {"x": jnp.asarray([x])})
    assert float(got) == pytest.approx(want, rel=1e-12)
    net = problem.make_network(jax.random.key(0))
    assert physgrad.parameter_count(net) == 1 * 7 + 7 + 7 * 2 + 2


def test_public_names_have_docstrings():
    for name in physgrad.__all__:
        obj = getattr(physgrad, name)
        if callable(obj) or isinstance(obj, type):
            assert (obj.__doc__ or "").strip(), name


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_paper_comparison_resolves_with_paper_defaults(name):
    from physgrad.study import plan

    configs = plan(name, None, [0], Budget(seconds=1))
    assert [c.method for c in configs] == list(PROBLEMS[name].default_methods)
    for config in configs:
        for phase in config.phases:
            paper = PROBLEMS[name].defaults_for(phase.method)
            assert phase.batch_size == paper["batch_size"]
            assert all(phase.hyperparameters[k] == v for k, v in paper.items() if k != "batch_size")

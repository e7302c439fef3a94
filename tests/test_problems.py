"""Every registered problem honours the contract; the HIG toy's loss against NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad import Budget
from physgrad.harness.config import make_config, phase_methods
from physgrad.harness.papers import protocol
from physgrad.harness.registry import METHODS, PROBLEMS, paper_defaults
from physgrad.harness.train import build
from physgrad.problems import HigToy

# The contract is a property of the code, not of the size: each problem is built at the
# smallest size that exercises every piece (data, network, loss, target), in seconds. The
# paper sizes are built by the slow tier (test_registered_problem_contract_at_paper_size)
# and exercised by the reproduction runs.
SMALL_DATA = {
    "ks": {"frames": "40", "warmup_frames": "20", "n_ics": "1", "n_test": "1", "long_horizon": "12",
           "dataset_fraction": "1.0", "width": "8", "blocks": "2"},
    "kolmogorov": {"n": "16", "refinement": "2", "forcing_mode": "4", "frames": "10", "warmup_frames": "10",
                   "n_test": "1", "long_horizon": "12", "width": "8", "blocks": "2"},
    "advection_1d": {"n_train": "4", "n_test": "2", "horizon": "16"},
    "heat": {"resolution": "16", "levels": "2", "filters": "4", "n_train": "8", "n_test": "8"},
    "poisson": {"resolution": "16", "levels": "2", "filters": "4", "n_train": "8", "n_test": "8"},
    "navier_stokes": {"resolution": "16", "size": "32.0", "box": "14.0", "swirl_sigma": "5.0", "falloff": "20.0",
                      "levels": "3", "filters": "4", "n_train": "8", "n_test": "4"},
    "quantum_dipole": {"n_train": "8", "n_test": "8", "n_steps": "48"},
    "poisson_hig": {"n_train": "32", "n_test": "32"},
    "quantum_control": {"n_train": "8", "n_test": "8", "n_steps": "16"},
    "cartpole": {"n_train": "8", "n_test": "8", "n_steps": "20"},
    "guidance": {"n_train": "8", "n_test": "8", "n_steps": "12"},
}  # fmt: skip
# What the slow tier builds at the paper's size (the rest are small at the paper's size too).
PAPER_SIZE = ["heat", "kolmogorov", "ks", "navier_stokes", "poisson"]


def check_contract(name, settings):
    cls = PROBLEMS[name]
    assert cls.name == name and protocol(name).description and cls.source and cls.__doc__
    for method in protocol(name).methods:
        assert set(phase_methods(method)) <= set(METHODS)
    b = str(min(8, cls.default_batch_size))  # toy2d optimises one x
    setup = build(make_config(name, "hig", budget=Budget(steps=1), settings={**settings, "batch_size": b}))
    batch = jax.tree.map(lambda a: a[: int(b)], setup.data["train"])
    sample = jax.tree.map(lambda a: a[0], batch)

    has_target = setup.objective.target is not None

    @jax.jit  # one program for the losses and (with a target) the first sample's prediction, not two
    def evaluate(params, batch, sample):
        y = setup.objective.predict(params, sample) if has_target else None
        return setup.objective.sample_losses(params, batch), y

    losses, y = evaluate(setup.params, batch, sample)
    assert losses.shape == (int(b),) and bool(jnp.all(jnp.isfinite(losses)))
    if has_target:  # SIP's y-space target has the simulator's shape
        assert setup.objective.target(sample).shape == y.shape
        assert float(setup.objective.loss(setup.objective.target(sample), sample)) == pytest.approx(0.0, abs=1e-6)
    # the same seed gives the same data and network
    again = build(make_config(name, "hig", budget=Budget(steps=1), settings={**settings, "batch_size": b}))
    for a, b in zip(jax.tree.leaves((setup.data, setup.params)), jax.tree.leaves((again.data, again.params))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# The problems whose data alone take most of a minute to generate (exponax's reference
# solvers, the fluid's rollouts) are built small by their own modules (test_unrolling,
# test_navier_stokes); their contract check runs in the slow tier.
HEAVY_DATA = ("heat", "kolmogorov", "ks", "navier_stokes")


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in HEAVY_DATA else n for n in sorted(PROBLEMS)]
)
def test_registered_problem_contract(name, tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path))
    cls = PROBLEMS[name]
    small = SMALL_DATA.get(name) or {k: "32" for k in ("n_train", "n_test") if k in cls.settings()}
    check_contract(name, small)


@pytest.mark.slow
@pytest.mark.parametrize("name", PAPER_SIZE)
def test_registered_problem_contract_at_paper_size(name, tmp_path, monkeypatch):
    """The paper's grid and network; only the data set's length kept short."""
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path))
    lengths = {"ks": ["frames", "warmup_frames", "n_ics", "n_test", "long_horizon", "dataset_fraction"],
               "kolmogorov": ["frames", "warmup_frames", "n_test", "long_horizon"]}  # fmt: skip
    keep = lengths.get(name, ["n_train", "n_test"])
    check_contract(name, {k: v for k, v in SMALL_DATA[name].items() if k in keep})


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
    from physgrad.harness.study import plan

    configs = plan(name, None, [0], Budget(seconds=1))
    assert [c.method for c in configs] == list(protocol(name).methods)
    for config in configs:
        for phase in config.phases:
            paper = paper_defaults(PROBLEMS[name], phase.method)
            assert phase.batch_size == paper["batch_size"]
            assert all(phase.hyperparameters[k] == v for k, v in paper.items() if k != "batch_size")

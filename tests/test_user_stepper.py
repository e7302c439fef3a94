"""A user's own exponax stepper as the solver of a time-stepper problem, the documented path
(README, "A neural time-stepper around your own solver"; examples/04_time_stepper_exponax.ipynb):
``physgrad.problems.sim.steppers.Repeated(exponax_stepper, substeps)`` as ``solvers()`` of a
``TimeStepperProblem`` subclass, trained by ``physgrad.unrolled`` in the user's loop (ONE,
NOG, WIG) and by ``physgrad.fit``; and ``zero_init`` on a user's multi-layer network."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
from physgrad.problems import TimeStepperProblem
from physgrad.problems.sim.steppers import Bypass, Parallel, Repeated, Residual, Solver, single_precision
from physgrad.rollout import R, S


def _conv_net(key, width=8):
    k1, k2 = jax.random.split(key)
    conv = lambda i, o, k: eqx.nn.Conv1d(i, o, 3, padding="SAME", padding_mode="CIRCULAR", dtype=jnp.float32, key=k)  # noqa: E731
    return eqx.nn.Sequential([conv(1, width, k1), eqx.nn.Lambda(jax.nn.tanh), conv(width, 1, k2)])


class _Decay(Solver):
    def __call__(self, u, cond):
        return 0.9 * u


class _SequentialDecay(TimeStepperProblem):
    name = "user_decay"
    description = "u_t = -u, a user's Sequential network"
    source = "tests"

    def generate(self, split):
        u0 = np.random.default_rng(0).normal(size=(2, 1, 1, 8))
        u = u0 * np.exp(-0.1 * np.arange(6))[None, :, None, None]
        return {"u": u.astype(np.float32), "cond": np.zeros(2, np.float32), "index": np.zeros(2, np.int32)}

    def solvers(self):
        return _Decay()

    def make_network(self, key):
        return _conv_net(key)

    def apply(self, network, u, cond):
        return network(u)


def test_zero_init_zeroes_only_the_last_layer_of_a_users_sequential_network():
    """The output layer, not every layer: zeroing them all leaves only the last bias with a
    gradient (the network could never learn)."""
    plain = _SequentialDecay(zero_init=False).initial_network(jax.random.key(0), {})
    net = _SequentialDecay(zero_init=True).initial_network(jax.random.key(0), {})
    np.testing.assert_array_equal(net.layers[0].weight, plain.layers[0].weight)
    assert not np.any(net.layers[2].weight) and not np.any(net.layers[2].bias)
    u = jnp.ones((1, 8), jnp.float32)
    np.testing.assert_array_equal(net(u), jnp.zeros_like(u))  # the corrector starts as the bare solver
    grads = eqx.filter_grad(lambda n: jnp.sum(n(jnp.linspace(0, 1, 8, dtype=jnp.float32)[None]) - 1.0) ** 2)(net)
    assert np.any(grads.layers[2].weight)  # the output layer learns from the first step
    eqx_mlp = eqx.nn.MLP(4, 4, 8, 2, dtype=jnp.float32, key=jax.random.key(1))
    mlp_problem = _SequentialDecay(zero_init=True)
    object.__setattr__(mlp_problem, "make_network", lambda key: eqx_mlp)
    zeroed = mlp_problem.initial_network(jax.random.key(0), {})
    assert not np.any(zeroed.layers[-1].weight) and np.array_equal(zeroed.layers[0].weight, eqx_mlp.layers[0].weight)


def test_setup_and_composition_strings_are_deprecated_spellings_of_composition_objects():
    with pytest.warns(DeprecationWarning, match="composition object") as warned:
        residual = _SequentialDecay(setup="prediction", composition="residual")
    assert warned[0].filename == __file__  # the user's line, past Equinox's __post_init__ frames
    assert residual.composition == Residual() and residual.setup is None
    with pytest.warns(DeprecationWarning):
        assert _SequentialDecay(composition="bypass").composition == Bypass(1.0)
    assert _SequentialDecay().composition == Parallel(1.0)


ex = pytest.importorskip("exponax", reason="the user's solver is an exponax stepper (physgrad[pde])")

N = 32
FINE = Repeated(ex.stepper.Burgers(1, 1.0, N, 0.01, diffusivity=0.02, order=2), substeps=4)
# coefficients rounded to float32 (the suite runs with x64 on, so exponax builds float64 ones;
# Repeated keeps the state's dtype either way, tested below)
COARSE = single_precision(Repeated(ex.stepper.Burgers(1, 1.0, N, 0.04, diffusivity=0.02, order=1)))


# the reference step compiled once, per state (1, N): eagerly each of its operations compiles on
# its own, again for every split's batch size
_fine = jax.jit(lambda v: FINE(v, None))


class _UserBurgers(TimeStepperProblem):
    name = "user_burgers"
    description = "a user's exponax Burgers stepper corrected towards a finer one"
    source = "tests"

    def generate(self, split):
        count, frames = {"train": (4, 6), "val": (1, 6), "test": (2, 6)}[split]
        x = jnp.arange(N) / N
        phase = jnp.arange(count)[:, None] * 0.7 + {"train": 0.0, "val": 0.3, "test": 0.5}[split]
        u = [jnp.sin(2 * jnp.pi * (x[None] + phase))[:, None]]  # (count, 1, N)
        for _ in range(frames):
            u.append(jnp.stack([_fine(v) for v in u[-1]]))  # one compiled step for every split and size
        return {"u": np.stack(u, 1).astype(np.float32), "cond": np.zeros(count, np.float32),
                "index": np.zeros(count, np.int32)}  # fmt: skip

    def solvers(self):
        return COARSE

    def make_network(self, key):
        return _conv_net(key)

    def apply(self, network, u, cond):
        return network(u)


@pytest.fixture(scope="module")
def burgers(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("PHYSGRAD_CACHE", str(tmp_path_factory.mktemp("cache")))
    problem = _UserBurgers(m=3, zero_init=True)
    data = problem.make_data(jax.random.key(0))
    yield problem, data
    mp.undo()


@pytest.mark.costly("the module fixture's first user: it generates the user's exponax Burgers data for all")
def test_a_users_exponax_stepper_is_a_solver_and_the_corrector_starts_at_it(burgers):
    problem, data = burgers
    u = data["train"]["u"][0, 0]
    np.testing.assert_allclose(COARSE(u, None), COARSE.stepper(u), rtol=0, atol=0)
    net = problem.initial_network(jax.random.key(1), data)
    out, ok = problem.step(lambda v, c: problem.apply(net, v, c), u, u, 0.0, 0)
    np.testing.assert_allclose(out, COARSE(u, None), atol=1e-7)
    assert bool(ok) and problem.solver_differentiable
    assert data["train"]["u"].shape == (4 * 4, 4, 1, N)  # windows of m + 1 = 4 frames


def _hand_rollout_loss(net, batch, modality, m=3):
    """The user's own m-step rollout loss: u⁺ = COARSE(u) + f(u), mean over steps of the MSE;
    ONE starts every step at the reference frame, NOG stops each state after its loss."""
    frames, u, total = batch["u"], batch["u"][:, 0], 0.0
    for k in range(m):
        u_in = frames[:, k] if modality == "one" else (jax.lax.stop_gradient(u) if modality == "nog" else u)
        u = jax.vmap(lambda v: COARSE(v, None) + net(v))(u_in)
        total = total + jnp.mean((u - frames[:, k + 1]) ** 2) / m
    return total


# ONE and NOG in the slow tier (as in test_unrolling): WIG differentiates through network and
# solver, the path the other two only cut; each case compiles a rollout and its gradient (~14 s)
@pytest.mark.parametrize(
    "modality", [pytest.param("one", marks=pytest.mark.slow), pytest.param("nog", marks=pytest.mark.slow), "wig"]
)
def test_one_nog_wig_of_a_users_exponax_corrector_are_the_hand_written_gradients(burgers, modality):
    """physgrad.unrolled on problem.system with the user's stepper gives the gradient of the
    user's own rollout written out by hand (ONE: teacher-forced, NOG: states stopped, WIG:
    through network and exponax solver), and a few Adam steps on it lower the loss."""
    problem, data = burgers
    system = problem.system(problem.apply, teacher_forcing=modality == "one")
    estimate = physgrad.unrolled(system, policy=R() if modality == "wig" else S())
    net = problem.initial_network(jax.random.key(2), data)
    net = eqx.tree_at(lambda n: n.layers[2].weight, net, 0.1 * jnp.ones_like(net.layers[2].weight))  # off zero
    batch = jax.tree.map(lambda a: a[:8], data["train"])
    direction, stats = eqx.filter_jit(estimate)(net, batch)
    # the hand-written loop compiled as one program (eagerly, each exponax operation of the
    # rollout and its gradient compiles on its own)
    loss, expected = eqx.filter_jit(eqx.filter_value_and_grad(_hand_rollout_loss))(net, batch, modality)
    assert float(stats["loss"]) == pytest.approx(float(loss), rel=1e-5) and bool(jnp.all(stats["solver_ok"]))
    for got, want in zip(jax.tree.leaves(direction), jax.tree.leaves(expected)):
        np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-7 * float(jnp.max(jnp.abs(want))))

    optimizer = optax.adam(1e-3)
    opt_state = optimizer.init(eqx.filter(net, eqx.is_inexact_array))

    @eqx.filter_jit
    def step(net, opt_state, batch):
        direction, stats = estimate(net, batch)
        updates, opt_state = optimizer.update(direction, opt_state, eqx.filter(net, eqx.is_inexact_array))
        return eqx.apply_updates(net, updates), opt_state, stats

    losses = []
    for _ in range(10):
        net, opt_state, stats = step(net, opt_state, batch)
        losses.append(float(stats["loss"]))
    assert np.isfinite(losses).all() and losses[-1] < losses[0]


def test_fit_trains_a_users_exponax_corrector(burgers, tmp_path):
    problem, _ = burgers
    nog = physgrad.methods.Unrolled(physgrad.methods.UnrolledGradient(policy=S()), lr=1e-3)
    summary = physgrad.fit(problem, nog, budget=physgrad.Budget(steps=20), out=tmp_path / "run")
    assert (tmp_path / "run" / "metrics.csv").exists()
    assert np.isfinite(summary["final_test_loss"] if "final_test_loss" in summary else list(summary.values())[0])


def test_nog_trains_a_users_exponax_stepper_declared_without_derivatives_and_wig_refuses(burgers):
    """``differentiable_solver=False`` wraps the user's stepper in ``NonDifferentiable``: NOG
    never calls its derivative; WIG's rollout needs it and is refused."""
    problem, data = burgers
    external = dataclasses.replace(problem, differentiable_solver=False)
    assert not external.solver_differentiable
    net = external.initial_network(jax.random.key(1), data)
    batch = jax.tree.map(lambda a: a[:4], data["train"])
    # jitted: one program, not the rollout's operations compiled one by one
    g, stats = eqx.filter_jit(physgrad.unrolled(external.system(external.apply), policy=S()))(net, batch)
    assert all(np.isfinite(leaf).all() for leaf in jax.tree.leaves(g)) and np.isfinite(float(stats["loss"]))
    with pytest.raises(Exception, match="differentiat"):
        physgrad.unrolled(external.system(external.apply), policy=R())(net, batch)


def test_repeated_keeps_the_states_dtype_when_the_stepper_was_built_with_x64():
    """The suite runs with x64 on, so exponax builds float64 coefficients: without the cast a
    float32 state would come back float64 and a rollout's scan would refuse the carry."""
    raw = Repeated(ex.stepper.Burgers(1, 1.0, N, 0.04, diffusivity=0.02, order=1), substeps=2)
    assert any(getattr(a, "dtype", None) in (jnp.float64, jnp.complex128) for a in jax.tree.leaves(raw))
    u = jnp.sin(2 * jnp.pi * jnp.arange(N, dtype=jnp.float32) / N)[None]
    out = raw(u, None)
    assert out.dtype == jnp.float32
    np.testing.assert_allclose(out, raw.stepper(raw.stepper(u.astype(jnp.float64))), rtol=1e-5, atol=1e-6)

    class RawBurgers(_UserBurgers):  # the solver as exponax built it, no single_precision
        def solvers(self):
            return raw

    problem = RawBurgers(m=3)
    frames = jnp.stack([u, out, out, out])[None]  # one window of m + 1 frames
    batch = {"u": frames, "cond": jnp.zeros(1, jnp.float32), "index": jnp.zeros(1, jnp.int32)}
    net = problem.initial_network(jax.random.key(0), {})
    g, stats = eqx.filter_jit(physgrad.unrolled(problem.system(problem.apply), policy=R()))(net, batch)  # one program
    assert np.isfinite(float(stats["loss"])) and all(np.isfinite(leaf).all() for leaf in jax.tree.leaves(g))

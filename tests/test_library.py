"""physgrad as a library: update rules inside a user's own loop with the user's optax chain,
and a user's own problem class trained by ``physgrad.fit`` with no registry.

Each update is compared with the same update composed by hand: the direction from an
independent NumPy float64 formula (SVD of J, pseudo-inverse, hand-written rollout loops),
then clipping and a learning-rate schedule written out in NumPy.
"""

from __future__ import annotations

import functools
import json
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

import physgrad
from physgrad.inverse import GaussNewton
from physgrad.methods import Gradient, JacobianPower, Method
from physgrad.problems import AbstractProblem

CLIP, LR0, DECAY = 0.05, 0.5, 0.5


def chain():
    """The user's chain: global-norm clipping, then SGD on an exponential-decay schedule."""
    return optax.chain(optax.clip_by_global_norm(CLIP), optax.sgd(optax.exponential_decay(LR0, 1, DECAY)))


def by_hand(theta, direction, t):
    """The same chain in NumPy: θ − lr_t · d · min(1, CLIP/‖d‖), lr_t = LR0 · DECAY^t."""
    norm = np.linalg.norm(direction)
    return theta - LR0 * DECAY**t * direction * min(1.0, CLIP / norm)


def user_loop(estimate, params, batches):
    """A user's own jitted training loop around a physgrad estimator."""
    optimizer = chain()

    @jax.jit
    def step(params, opt_state, batch):
        direction, stats = estimate(params, batch)
        updates, opt_state = optimizer.update(direction, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, stats

    opt_state, path = optimizer.init(params), []
    for batch in batches:
        params, opt_state, stats = step(params, opt_state, batch)
        path.append(params)
    return path


# --- a small network through nonlinear physics: y = (z₀, z₁², sin z₂) -----------------------
def network(key):
    return physgrad.MLP((2, 6, 3), jax.nn.tanh, key=key)


def physics(z):
    return jnp.stack([z[0], 0.5 * z[1] ** 2, jnp.sin(z[2])])


def pieces(key=0):
    params, static = eqx.partition(network(jax.random.key(key)), eqx.is_inexact_array)

    def predict(p, sample):
        return physics(eqx.combine(p, static)(sample["x"]))

    def loss(y, sample):
        return 0.5 * jnp.sum((y - sample["y"]) ** 2)

    xs = jax.random.normal(jax.random.key(1), (2, 4, 2))
    ys = jax.random.normal(jax.random.key(2), (2, 4, 3))
    batches = [{"x": xs[i], "y": ys[i]} for i in range(2)]
    return params, predict, loss, batches


@functools.cache
def per_sample_pieces(predict, loss):
    """One sample's Jacobian of ``predict`` with respect to the flat parameters, and ∂L/∂y,
    each compiled once per test (eagerly, every operation of the reverse pass compiles on its
    own: most of the test's CPU)."""

    def jacobian(params, sample):
        flat, unravel = ravel_pytree(params)
        return jax.jacrev(lambda t: predict(unravel(t), sample))(flat)

    def gradient(params, sample):
        return jax.grad(loss)(predict(params, sample), sample)

    return jax.jit(jacobian), jax.jit(gradient)


def kappa_power_reference(predict, loss, params, batch, exponent, truncation):
    """V Σ^κ Uᵀ g in float64 NumPy from the per-sample Jacobians (SVD, σ ≤ τσ_max dropped)."""
    jacobian, gradient = per_sample_pieces(predict, loss)
    rows, grads = [], []
    for i in range(batch["x"].shape[0]):
        sample = jax.tree.map(lambda a: a[i], batch)
        rows.append(np.asarray(jacobian(params, sample), np.float64))
        grads.append(np.asarray(gradient(params, sample), np.float64) / batch["x"].shape[0])
    jac, g = np.concatenate(rows), np.concatenate(grads)
    u, s, vt = np.linalg.svd(jac, full_matrices=False)
    keep = s > truncation * s.max()
    return vt[keep].T @ (s[keep] ** exponent * (u[:, keep].T @ g))


@pytest.mark.parametrize("name,exponent", [("hig", -0.5), ("gauss_newton", -1.0)])
def test_jacobian_rules_in_a_user_loop_with_clipping_and_a_schedule(name, exponent):
    params, predict, loss, batches = pieces()
    estimate = getattr(physgrad, name)(predict, loss, truncation=1e-6, route=physgrad.routes.Gram())
    path = user_loop(estimate, params, batches)
    theta, unravel = ravel_pytree(params)
    theta = np.asarray(theta, np.float64)
    for t, batch in enumerate(batches):
        d = kappa_power_reference(predict, loss, unravel(jnp.asarray(theta, jnp.float32)), batch, exponent, 1e-6)
        theta = by_hand(theta, d, t)
        np.testing.assert_allclose(np.asarray(ravel_pytree(path[t])[0]), theta, rtol=2e-4, atol=2e-5)


def test_mlp_takes_its_activation_as_a_function_and_names_are_deprecated():
    with pytest.warns(DeprecationWarning, match="MLP") as warned:
        named = physgrad.MLP((2, 6, 3), "tanh", key=jax.random.key(0))
    assert warned[0].filename == __file__  # the warning names the user's line, not Equinox's
    assert named == network(jax.random.key(0))
    x = jnp.ones(2)
    np.testing.assert_allclose(named(x), network(jax.random.key(0))(x))


@pytest.mark.unchecked("a route given as a string on purpose: hig's own one-line error")
def test_routes_are_interchangeable_objects():
    params, predict, loss, batches = pieces()
    # Each estimate compiled as one program (eagerly, each operation compiles on its own: twice
    # the CPU); test_jit_estimators checks that a jitted estimate equals the eager one.
    directions = [
        ravel_pytree(jax.jit(physgrad.hig(predict, loss, route=route))(params, batches[0])[0])[0]
        for route in (
            physgrad.routes.SVD(),
            physgrad.routes.Gram(),
            physgrad.routes.BlockGram(2),
            physgrad.routes.Auto(),
        )
    ]
    for d in directions[1:]:
        np.testing.assert_allclose(np.asarray(d), np.asarray(directions[0]), rtol=2e-3, atol=1e-5)
    with pytest.raises(ValueError, match="route must be"):
        physgrad.hig(predict, loss, route="gram")


def test_sip_in_a_user_loop_with_clipping_and_a_schedule():
    """Network x = f(input); physics y = A x (well-conditioned 3×3); SIP with Gauss–Newton's
    local inverse gives x̃ = x + A⁻¹(y* − y): the proxy gradient by hand is Jᵀ(x − x̃)/b."""
    a = np.array([[2.0, 0.3, 0.0], [0.1, 1.0, 0.2], [0.0, 0.4, 3.0]], np.float32)
    params, static = eqx.partition(physgrad.MLP((2, 5, 3), jax.nn.tanh, key=jax.random.key(3)), eqx.is_inexact_array)

    def network_output(p, sample):
        return eqx.combine(p, static)(sample["x"])

    def simulate(x, sample):
        return jnp.asarray(a) @ x

    estimate = physgrad.sip(network_output, simulate, lambda s: s["y"], solver=GaussNewton(rcond=1e-6))
    batches = [{"x": jax.random.normal(jax.random.key(4 + i), (4, 2)), "y": jax.random.normal(jax.random.key(8 + i), (4, 3))}
               for i in range(2)]  # fmt: skip
    path = user_loop(estimate, params, batches)
    theta, unravel = ravel_pytree(params)
    theta = np.asarray(theta, np.float64)
    # x and ∂x/∂θ of one sample, each compiled once (eagerly, every operation compiles on its own)
    output_of = jax.jit(lambda th, sample: network_output(unravel(th), sample))
    jacobian_of = jax.jit(jax.jacrev(lambda th, sample: network_output(unravel(th), sample)))
    for t, batch in enumerate(batches):
        th = jnp.asarray(theta, jnp.float32)
        grad = np.zeros_like(theta)
        for i in range(4):
            sample = jax.tree.map(lambda v: v[i], batch)
            x = np.asarray(output_of(th, sample), np.float64)
            x_tilde = x + np.linalg.solve(a.astype(np.float64), np.asarray(sample["y"], np.float64) - a @ x)
            jac = np.asarray(jacobian_of(th, sample), np.float64)
            grad += jac.T @ (x - x_tilde) / 4
        theta = by_hand(theta, grad, t)
        np.testing.assert_allclose(np.asarray(ravel_pytree(path[t])[0]), theta, rtol=2e-4, atol=2e-5)


def test_stabilised_bptt_in_a_user_loop_with_clipping_and_a_schedule():
    """A scalar closed loop s' = s + 0.1·(s² − c), c = w·s + b, 4 steps, final loss s₄²; the
    hand-written gradients of R (true BPTT) and M (stop-gradient on the network input)
    are combined with the sign mask, then clipped and stepped by hand."""
    m = 4

    def control(p, s):
        return p["w"] * s + p["b"]

    def physics(s, c):
        return s + 0.1 * (s**2 - c)

    def step_loss(s_next, c, k):
        return s_next**2

    weights = jnp.zeros((m,)).at[-1].set(1.0)
    system = physgrad.closed_loop(control, physics, step_loss, m, weights)
    estimate = physgrad.stabilised_bptt(system)
    params = {"w": jnp.asarray(0.3), "b": jnp.asarray(-0.2)}
    batches = [jnp.array([0.8, -0.5, 1.2]), jnp.array([0.4, 0.9, -1.1])]
    path = user_loop(estimate, params, batches)

    def rollout_loss(p, s0, stop_network):
        s = s0
        for _ in range(m):
            c = control(p, jax.lax.stop_gradient(s) if stop_network else s)
            s = physics(s, c)
        return jnp.mean(s**2)

    theta = np.array([0.3, -0.2])
    for t, s0 in enumerate(batches):
        p = {"w": jnp.asarray(theta[0]), "b": jnp.asarray(theta[1])}
        g_r = jax.grad(rollout_loss)(p, s0, False)
        g_m = jax.grad(rollout_loss)(p, s0, True)
        g_r, g_m = np.array([g_r["b"], g_r["w"]]), np.array([g_m["b"], g_m["w"]])  # ravel order: b, w
        g_c = np.where(np.sign(g_m) == np.sign(g_r), g_m, 0.0)
        theta_bw = by_hand(np.array([theta[1], theta[0]]), g_c, t)
        theta = np.array([theta_bw[1], theta_bw[0]])
        np.testing.assert_allclose([float(path[t]["w"]), float(path[t]["b"])], theta, rtol=1e-5, atol=1e-7)


def test_multisteps_and_apply_if_finite_compose_unchanged():
    params, predict, loss, batches = pieces()
    # The estimate and the optimizer's update each compiled once as one program, as a user's
    # jitted loop runs them (eagerly, every operation of both compiles on its own: 3x the CPU).
    estimate = jax.jit(physgrad.hig(predict, loss))
    optimizer = optax.apply_if_finite(optax.MultiSteps(optax.sgd(0.5), every_k_schedule=2), max_consecutive_errors=3)
    update = jax.jit(optimizer.update)
    state = optimizer.init(params)
    d0, _ = estimate(params, batches[0])
    d1, _ = estimate(params, batches[1])
    updates, state = update(d0, state, params)
    assert all(float(jnp.max(jnp.abs(u))) == 0 for u in jax.tree.leaves(updates))  # accumulating
    updates, state = update(d1, state, params)
    expected = jax.tree.map(lambda a, b: -0.5 * (a + b) / 2, d0, d1)
    for u, e in zip(jax.tree.leaves(updates), jax.tree.leaves(expected)):
        np.testing.assert_allclose(u, e, rtol=1e-6, atol=1e-8)
    nan = jax.tree.map(lambda a: jnp.full_like(a, jnp.nan), d0)
    updates, state = update(nan, state, params)
    assert all(float(jnp.max(jnp.abs(u))) == 0 for u in jax.tree.leaves(updates))  # skipped


# --- a user's own problem class, trained by physgrad.fit with no registry --------------------
class Cubic(AbstractProblem):
    """Recover x from y = x + 0.1·x³ (per component) with a small MLP."""

    n: int = 256
    name: ClassVar[str] = "cubic"
    description: ClassVar[str] = "a test problem"
    source: ClassVar[str] = "this test"

    def make_data(self, key):
        x = jax.random.uniform(key, (2 * self.n, 2), jnp.float32, -1.0, 1.0)
        data = {"x": x, "y": x + 0.1 * x**3}
        return {"train": jax.tree.map(lambda a: a[: self.n], data), "test": jax.tree.map(lambda a: a[self.n :], data)}

    def make_network(self, key):
        return physgrad.MLP((2, 16, 2), jax.nn.tanh, key=key)

    def network_output(self, network, sample):
        return network(sample["y"])

    def simulate(self, x, sample):
        return x + 0.1 * x**3

    def loss(self, y, sample):
        return jnp.sum((y - sample["y"]) ** 2)

    def target(self, sample):
        return sample["y"]


def test_a_user_problem_trains_through_fit_without_a_registry(tmp_path):
    from physgrad.harness import registry

    assert "cubic" not in registry.PROBLEMS
    methods = {
        "adam": Method(Gradient(), optax.adam(1e-2)),
        "hig": Method(JacobianPower(-0.5), optax.sgd(0.5)),
        "sip": Method(physgrad.methods.ScaleInvariantPhysics(GaussNewton()), optax.adam(1e-2)),
    }
    for name, method in methods.items():
        summary = physgrad.fit(Cubic(), method, budget=physgrad.Budget(steps=60), out=tmp_path / name, batch_size=32,
                               settings=physgrad.TrainSettings(eval_every=20))  # fmt: skip
        assert summary["status"] == "finished" and summary["steps"] == 60
        metrics = physgrad.engine.read_metrics(tmp_path / name / "metrics.csv")
        test = [r["value"] for r in metrics if r["split"] == "test" and r["metric"] == "loss"]
        assert test[-1] < 0.5 * test[0], (name, test)
    assert "cubic" not in registry.PROBLEMS
    # resume with a larger budget continues from the checkpoint; the record matches
    record = json.loads((tmp_path / "adam" / "config.json").read_text())
    assert "Cubic" in record["problem"]
    more = physgrad.fit(Cubic(), methods["adam"], budget=physgrad.Budget(steps=80), out=tmp_path / "adam", batch_size=32,
                        settings=physgrad.TrainSettings(eval_every=20), resume=True)  # fmt: skip
    assert more["steps"] == 80
    with pytest.raises(physgrad.ConfigError, match="different configuration"):
        physgrad.fit(
            Cubic(n=128), methods["adam"], budget=physgrad.Budget(steps=90), out=tmp_path / "adam", resume=True
        )
    network = physgrad.load_network(tmp_path / "adam", like=Cubic().make_network(jax.random.key(0)))
    assert isinstance(network, physgrad.MLP)


def test_phases_hand_over_parameters(tmp_path):
    phases = [physgrad.Phase(Method(Gradient(), optax.adam(1e-2)), steps=10, batch_size=32, name="adam"),
              physgrad.Phase(Method(JacobianPower(-0.5), optax.sgd(0.5)), batch_size=16, name="hig")]  # fmt: skip
    summary = physgrad.fit(Cubic(), phases, budget=physgrad.Budget(steps=15), out=tmp_path / "run")
    assert summary["stage_steps"] == {"0:adam": 10, "1:hig": 5} and summary["method"] == "adam,hig"

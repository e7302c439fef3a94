"""How a rule's step changes when the per-sample loss is multiplied by c (a mean over the
output cells instead of a sum: c = 1/n), docs/methods.md, "Step size and the loss
normalisation": the HIG, Gauss–Newton and Levenberg–Marquardt directions V f(Σ) Uᵀ g are
linear in g = ∂L/∂y and J does not change, so each is c times its direction for L (p = 1);
Adam's update does not change (up to its ε). Checked against a NumPy float64 reference
built from a finite-difference Jacobian and a hand-written g."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

import physgrad
from physgrad.methods import JacobianPower
from physgrad.precision import float64_scope
from physgrad.routes import Damped
from test_methods import central_differences

B, TAU = 5, 1e-3  # τ keeps the finite-difference Jacobian's error from being amplified by σ^κ
SCALES = (1 / 64, 64.0)
# the "simulator": a fixed linear map with scales over two decades, coupling the outputs
PHYSICS = np.array([[1.0, 0.3, 0.0, 0.0], [0.0, 10.0, 0.0, 0.0], [0.0, 0.0, 0.1, 0.0], [0.2, 0.0, 0.0, 1.0]])


def predict(params, sample):
    hidden = jnp.tanh(params["w1"] @ sample["q"] + params["b1"])
    return jnp.asarray(PHYSICS) @ (params["w2"] @ hidden + params["b2"])


def summed(y, sample):
    return 0.5 * jnp.sum((y - sample["target"]) ** 2)


def scaled(c):
    return lambda y, sample: c * summed(y, sample)


def problem():
    rng = np.random.default_rng(0)
    params = {
        "w1": jnp.asarray(rng.normal(size=(6, 3))), "b1": jnp.asarray(0.1 * rng.normal(size=6)),
        "w2": jnp.asarray(rng.normal(size=(4, 6)) / 3), "b2": jnp.zeros(4),
    }  # fmt: skip
    batch = {"q": jnp.asarray(rng.normal(size=(B, 3))), "target": jnp.asarray(rng.normal(size=(B, 4)))}
    return params, batch


@functools.cache
def finite_difference_jacobian():
    """J by central differences of the outputs, and the outputs y, at problem()'s θ in float64:
    the same for every c and spectrum, so computed once."""
    with float64_scope():
        params, batch = problem()
        flat, unravel = ravel_pytree(params)
        flat = np.asarray(flat)
        outputs = lambda theta: jax.vmap(lambda s: predict(unravel(theta), s))(batch).ravel()  # noqa: E731
        return central_differences(outputs, flat), np.asarray(jax.jit(outputs)(jnp.asarray(flat)))


def numpy_reference(batch, c, spectrum):
    """V f(Σ) Uᵀ g with J from central differences and g = c (y − y*) / b, in float64."""
    jac, y = finite_difference_jacobian()
    g = c * (y - np.asarray(batch["target"]).ravel()) / B
    u, s, vt = np.linalg.svd(jac, full_matrices=False)
    keep = s > TAU * s.max()
    if isinstance(spectrum, Damped):
        f = s[keep] / (s[keep] ** 2 + spectrum.damping * s.max() ** 2)
    else:
        f = s[keep] ** spectrum
    return vt[keep].T @ (f * (u[:, keep].T @ g))


@pytest.mark.parametrize("spectrum", [-0.5, -1.0, Damped(1e-2)], ids=["hig", "gauss_newton", "lm"])
def test_jacobian_rules_scale_linearly_with_the_loss(spectrum):
    with float64_scope():
        params, batch = problem()
        rule = JacobianPower(-0.5, TAU)  # the exponent is replaced by `spectrum` in `filtered`

        # c an argument of one compiled program (eagerly, every operation compiles on its own:
        # 3x the CPU); c = 1/64 and 64 are powers of two, so c·L is exact either way
        @jax.jit
        def filtered(c):
            objective = physgrad.Objective(predict, scaled(c))
            return ravel_pytree(rule.filtered(objective, params, batch, spectrum)[0])[0]

        def direction(c):
            return np.asarray(filtered(jnp.float64(c)))

        base = direction(1.0)
        for c in SCALES:
            got = direction(c)
            want = numpy_reference(batch, c, spectrum)
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
            np.testing.assert_allclose(got, c * base, rtol=1e-12, atol=1e-14 * np.abs(got).max())


def test_hig_estimator_direction_scales_with_c():
    # the public entry point, default route (structured for this wide J), float32 network
    params, batch = problem()
    params, batch = jax.tree.map(lambda a: a.astype(jnp.float32), (params, batch))
    base = np.asarray(ravel_pytree(jax.jit(physgrad.hig(predict, summed))(params, batch)[0])[0])
    # c a float32 argument of one compiled estimate (eagerly, every operation compiles on its own)
    scaled_hig = jax.jit(lambda p, b, c: physgrad.hig(predict, scaled(c))(p, b)[0])
    for c in SCALES:
        got = np.asarray(ravel_pytree(scaled_hig(params, batch, jnp.float32(c)))[0])
        np.testing.assert_allclose(got, c * base, rtol=1e-4, atol=1e-6 * np.abs(got).max())


def test_adam_update_does_not_change():
    with float64_scope():
        params, batch = problem()

        # ε far below every |gradient| entry: at c = 1/64 some are ~1e-6, where the default
        # ε = 1e-8 would move the update by ~1 %; the invariance holds while |g| ≫ ε
        opt = optax.adam(1e-2, eps=1e-12)

        @jax.jit  # one program for every c and step (eagerly, every operation compiles on its own)
        def step(p, state, c):
            loss = lambda p: jnp.mean(jax.vmap(lambda s: scaled(c)(predict(p, s), s))(batch))  # noqa: E731
            updates, state = opt.update(jax.grad(loss)(p), state, p)
            return optax.apply_updates(p, updates), state

        def trajectory(c, steps=3):
            p, state = params, opt.init(params)
            for _ in range(steps):
                p, state = step(p, state, jnp.float64(c))
            return np.asarray(ravel_pytree(p)[0])

        base = trajectory(1.0)
        for c in SCALES:
            np.testing.assert_allclose(trajectory(c), base, rtol=1e-7, atol=1e-10)  # up to ε

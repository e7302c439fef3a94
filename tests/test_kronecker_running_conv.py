"""KHIG's running factors on convolution layers (``AveragedKronecker`` through the signal route).

References: each step's fresh KFC factors from ``conv_factors.conv_layer_factors`` (checked
against explicit NumPy patch sums in ``tests/test_kronecker_conv.py``), averaged by hand in
NumPy; their eigendecompositions by ``numpy.linalg.eigh`` on the refresh steps only; the
gradient from ``jax.grad``; the layer's direction ``Q_G [φ(γαᵀ/(bT)) ⊙ (Q_Gᵀ ∇K̄ Q_A)] Q_Aᵀ``
written out in NumPy. The fresh rule (``KroneckerPower``) for β = 0 with every period 1.
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
from physgrad.methods import AveragedKronecker, KroneckerPower, RunningFactors, layer_terms
from physgrad.methods import conv_factors as kfc
from test_kronecker_conv import DY, B, _two_layer


def _batches(n):
    keys = jax.random.split(jax.random.key(21), 2 * n)
    return [{"x": jax.random.normal(keys[2 * i], (B, 3, 8), jnp.float64),
             "t": jax.random.normal(keys[2 * i + 1], (B, DY), jnp.float64)} for i in range(n)]  # fmt: skip


def _full(grads, name):
    return np.concatenate([np.asarray(grads[name].weight).reshape(3, -1), np.asarray(grads[name].bias).reshape(3, 1)],
                          axis=1)  # fmt: skip


def test_layer_pass_gradients_equal_patch_products_and_jax_grad():
    """``layer_pass``'s ∇K̄ (the kernel operand tapped, no patches) equals the patch product
    Σ D_gᵀ p̄ (``conv_factors.layer_signals`` and ``conv_patches``) and ``jax.grad`` reshaped
    (out, in·k) with the bias last; its counts are b·T; the loss is the batch mean."""
    params, batch, predict, loss, *_ = _two_layer()
    objective = physgrad.Objective(predict, loss)
    plan = KroneckerPower().plan(objective, params, batch)
    args = (plan.structure, plan.structure.dense, plan.convs, params, batch, plan.jacobian.loss_and_gradient)
    grads, counts, value = jax.jit(lambda: (lambda r: (r.grads, r.counts, r.loss))(layer_terms.layer_pass(*args, 0)))()
    sig, *_ = jax.jit(lambda: kfc.layer_signals(*args, 0))()
    # the references compiled as one program each (eagerly, each operation of the conv network's
    # reverse pass and of the patch extraction compiles on its own: most of the test's CPU)
    want = jax.jit(jax.grad(lambda p: jnp.mean(jax.vmap(lambda s: loss(predict(p, s), s))(batch))))(params)
    assert [c.leaf for c in plan.convs] == [0, 2]  # leaves: c1's kernel and bias, then c2's
    for c, x, d_g, fast, name in zip(plan.convs, sig.x, sig.d_g, grads, ("c1", "c2")):
        p = np.asarray(jax.jit(lambda x: kfc.conv_patches(plan.structure, c, x))(x))
        p = np.concatenate([p, np.ones((p.shape[0], 1))], axis=1)
        d = np.asarray(jax.jit(lambda d_g: kfc.conv_signals(plan.structure, c, d_g))(d_g)).reshape(-1, 3)
        np.testing.assert_allclose(np.asarray(fast), d.T @ p, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(fast), _full(want, name), rtol=1e-12, atol=1e-14)
    assert counts == [B * 8, B * 4]  # b·T: 8 positions, then 4 (stride 2)
    np.testing.assert_allclose(float(value), float(jnp.mean(jax.vmap(lambda s: loss(predict(params, s), s))(batch))),
                               rtol=1e-14)  # fmt: skip


def test_running_conv_factors_without_averaging_equal_the_fresh_rule():
    params, batch, predict, loss, *_ = _two_layer()
    objective = physgrad.Objective(predict, loss)
    rule = KroneckerPower(-0.75, 1e-6, 1e-3)
    fresh = physgrad.Method(rule, optax.sgd(0.05))
    averaged = AveragedKronecker(rule, optax.sgd(0.05), curvature_ema=0.0, inverse_every=1)
    p_f, s_f, p_a, s_a = params, fresh.init(params), params, averaged.init(params)
    fresh_step = jax.jit(fresh.step, static_argnums=0)  # once: both steps run one program each
    averaged_step = jax.jit(averaged.step, static_argnums=0)
    for b in _batches(2):
        p_f, s_f, _ = fresh_step(objective, p_f, s_f, b)
        p_a, s_a, stats = averaged_step(objective, p_a, s_a, b)
        assert int(stats["refreshed"]) == 1
    for a, f in zip(jax.tree.leaves(p_a), jax.tree.leaves(p_f)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(f), rtol=1e-10, atol=1e-12)


@pytest.mark.costly("the only check of the conv layers' running factors and their periods against a reference")
@pytest.mark.parametrize(("curvature_every", "inverse_every"), [(1, 2), (2, 4)])
def test_running_conv_factors_collect_and_refresh_on_their_periods(curvature_every, inverse_every):
    """Five steps: the factors enter the average (β) only on steps t ≡ 0 mod curvature_every,
    their eigendecompositions are recomputed only on t ≡ 0 mod inverse_every, and every step's
    direction is the power of the last eigendecomposition applied to that step's own gradient."""
    params, _, predict, loss, *_ = _two_layer()
    beta, lr, damping, power = 0.6, 0.05, 1e-3, -0.75
    objective = physgrad.Objective(predict, loss)
    method = AveragedKronecker(KroneckerPower(power, 0.0, damping), optax.sgd(lr), curvature_ema=beta,
                               inverse_every=inverse_every, curvature_every=curvature_every)  # fmt: skip
    step = jax.jit(method.step, static_argnums=0)
    factors = jax.jit(lambda p, b: kfc.conv_layer_factors(predict, p, b))
    gradient = jax.jit(jax.grad(lambda p, b: jnp.mean(jax.vmap(lambda s: loss(predict(p, s), s))(b))))
    state, averages, eig = method.init(params), [None, None], [None, None]
    for t, b in enumerate(_batches(5)):
        new, state, stats = step(objective, params, state, b)
        assert int(stats["refreshed"]) == (t % inverse_every == 0)
        fresh, grads = factors(params, b), gradient(params, b)
        for k, name in enumerate(("c1", "c2")):
            if t % curvature_every == 0:
                pair = (np.asarray(fresh[k].A), np.asarray(fresh[k].G))
                averages[k] = (
                    pair if t == 0 else tuple(beta * old + (1 - beta) * m for old, m in zip(averages[k], pair))
                )
            if t % inverse_every == 0:
                eig[k] = (np.linalg.eigh(averages[k][0]), np.linalg.eigh(averages[k][1]))
            (alpha, q_a), (gamma, q_g) = eig[k]
            lam = np.maximum(np.outer(gamma, alpha), 0) / fresh[k].count
            phi = (lam + damping * lam.max()) ** power
            want = q_g @ (phi * (q_g.T @ _full(grads, name) @ q_a)) @ q_a.T
            got = (_full(params, name) - _full(new, name)) / lr
            np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())
            left, right = state.control.factors[2 * k]  # the kernel leaf (out, in, k): G left, A right
            np.testing.assert_allclose(np.asarray(left)[:3, :3], averages[k][1], rtol=1e-12)
            np.testing.assert_allclose(np.asarray(right)[:10, :10], averages[k][0], rtol=1e-12)
        params = new


def test_running_factors_refusals():
    with pytest.raises(ValueError, match=r"^curvature_every must be >= 1 and divide inverse_every=4, got 3$"):
        RunningFactors(0.9, 4, 3)
    wide = {"k": jnp.zeros((2, 64, 64, 3))}  # in·window = 12288 ≥ 4096: no running factors kept

    def predict(p, s):
        return jax.lax.conv_general_dilated(s["x"][None], p["k"], (1, 1), "VALID").ravel()

    objective = physgrad.Objective(predict, lambda y, s: jnp.sum(y**2))
    method = AveragedKronecker(KroneckerPower(), optax.sgd(0.1), curvature_ema=0.5, inverse_every=2)
    batch = {"x": jnp.zeros((2, 64, 64, 5))}
    with pytest.raises(ValueError, match=r"^khig: running factors of leaf 0 \(shape \(2, 64, 64, 3\)\) do not fit"):
        method.step(objective, wide, method.init(wide), batch)


@pytest.mark.slow  # minutes of compilation on a shared CPU; the directions are checked above
def test_khig_with_running_factors_trains_a_unet_problem(tmp_path):
    """8 steps of khig with factors collected and eigendecomposed every 4 steps lower poisson's test loss."""
    from cli_training import cli_test_losses
    from test_kronecker_conv import UNET_SMALL

    settings = {**UNET_SMALL["poisson"], "batch_size": "8", "eval_every": "4", "probes": "4", "lr": "0.001",
                "damping": "0.1", "curvature_ema": "0.9", "inverse_every": "4", "curvature_every": "4"}  # fmt: skip
    test = cli_test_losses(tmp_path / "run", "poisson", "khig", 8, settings)
    assert len(test) == 3 and all(np.isfinite(test)), test
    assert test[-1] < test[0], test

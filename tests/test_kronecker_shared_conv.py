"""KHIG on a convolution kernel shared by several convolutions (a network unrolled over steps).

The rollout is written twice: as a Python loop (one convolution equation per step) and as
a ``lax.scan`` over a jitted step (the convolution inside nested programs, inlined by
``physgrad.methods.conv_program``); both must give the same factors and direction.

References: per use u of the kernel, its input patches written out by hand in NumPy
(``numpy.pad(mode="wrap")``, as the KS corrector's circular padding) and its signals
``D^u = ∂y/∂z_u`` from ``jax.jacfwd`` with respect to a perturbation of that use's output
alone; the check ``Σ_u Σ_t D^u_t ⊗ p^u_tᵀ = J_K`` against ``jax.jacfwd`` of the output with
respect to the kernel itself (the uses' terms add up to the total derivative); then the
explicit sums ``A = Σ_u Σ_i Σ_t p̄ p̄ᵀ``, ``G = Σ_u Σ_i Σ_t DᵀD`` and the power of
``kron(G, A)/(b Σ_u T_u)`` (``numpy.linalg.eigh``) applied to ``jax.grad``'s gradient.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
from physgrad.methods import AveragedKronecker, KroneckerPower
from physgrad.methods import conv_factors as kfc
from test_kronecker_conv import _np_patches, _np_power

B, C, N, DY, STEPS = 3, 2, 8, 5, 3


def _rollout():
    """u_{k+1} = u_k + ½ f(u_k) for STEPS steps with one circular Conv1d f (C → C, kernel 3,
    bias), y = sin(M [u_1; …; u_STEPS]): the kernel and the bias are read once per step."""
    keys = jax.random.split(jax.random.key(31), 4)
    conv = eqx.nn.Conv(1, C, C, 3, padding="SAME", padding_mode="CIRCULAR", key=keys[0], dtype=jnp.float64)
    params, static = eqx.partition(conv, eqx.is_inexact_array)
    M = jax.random.normal(keys[1], (DY, STEPS * C * N), jnp.float64) / np.sqrt(STEPS * C * N)
    batch = {"x": jax.random.normal(keys[2], (B, C, N), jnp.float64), "t": jax.random.normal(keys[3], (B, DY))}

    def run(p, x, eps=None):  # eps[k]: a perturbation of step k's convolution output
        states = []
        for k in range(STEPS):
            z = eqx.combine(p, static)(x)
            x = x + 0.5 * jnp.tanh(z if eps is None else z + eps[k])
            states.append(x)
        return jnp.sin(M @ jnp.concatenate(states).ravel()), states

    def predict(p, s):
        return run(p, s["x"])[0]

    def scanned(p, s):  # the same rollout as a lax.scan over a jitted step: the convolutions are inlined
        step = jax.jit(lambda x: x + 0.5 * jnp.tanh(eqx.combine(p, static)(x)))
        _, states = jax.lax.scan(lambda x, _: (lambda y: (y, y))(step(x)), s["x"], None, length=STEPS)
        return jnp.sin(M @ states.ravel())

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    return params, batch, {"loop": predict, "scan": scanned}, loss, run


def _explicit(params, batch, run):
    """A, G over every use and sample from NumPy patches and jacfwd signals."""

    @jax.jit
    def jacobians(params, xs):
        def one(x):
            eps = jnp.zeros((STEPS, C, N), jnp.float64)
            D = jax.jacfwd(lambda e: run(params, x, e)[0])(eps)  # (dy, steps, C, N)
            J_K = jax.jacfwd(lambda w: run(eqx.tree_at(lambda m: m.weight, params, w), x)[0])(params.weight)
            inputs = jnp.stack([x] + run(params, x)[1][:-1])  # each use's input
            return D, J_K, inputs

        return jax.vmap(one)(xs)

    Ds, J_Ks, inputs = (np.asarray(a) for a in jacobians(params, batch["x"]))
    A = G = 0.0
    for D, J_K, xs in zip(Ds, J_Ks, inputs):
        rebuilt = 0.0
        for u in range(STEPS):
            p = _np_patches(xs[u], 3, 1, 1, 1, "wrap")  # (T, C·3)
            rebuilt = rebuilt + np.einsum("rot,tf->rof", D[:, u], p)
            p_bar = np.concatenate([p, np.ones((p.shape[0], 1))], axis=1)
            A = A + p_bar.T @ p_bar
            G = G + np.einsum("rot,rqt->oq", D[:, u], D[:, u])
        np.testing.assert_allclose(rebuilt, J_K.reshape(DY, C, -1), atol=1e-12)  # the uses add up to J_K
    return A, G


@pytest.mark.parametrize("form", ["loop", "scan"])
def test_shared_kernel_factors_sum_over_its_uses(form):
    params, batch, predicts, _, run = _rollout()
    predict = predicts[form]
    (found,) = jax.jit(lambda p, b: kfc.conv_layer_factors(predict, p, b))(params, batch)
    A, G = _explicit(params, batch, run)
    assert (int(found.kernel), int(found.bias)) == (0, 1)  # leaves: weight, bias (shared too)
    assert found.count == B * STEPS * N  # b · Σ_u T_u
    np.testing.assert_allclose(np.asarray(found.A), A, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(found.G), G, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(("form", "running"), [("loop", False), ("scan", False), ("loop", True)])
def test_shared_kernel_direction_is_the_power_of_its_summed_block(form, running):
    """ΔK̄ = φ(kron(G, A)/(b Σ_u T_u)) vec(∇K̄), ∇K̄ from jax.grad (the sum over uses); the
    running factors with β = 0 and every period 1 give the same step."""
    params, batch, predicts, loss, run = _rollout()
    predict = predicts[form]
    power, damping = -0.75, 1e-3
    rule = KroneckerPower(power, 0.0, damping)
    objective = physgrad.Objective(predict, loss)
    if running:
        method = AveragedKronecker(rule, optax.sgd(1.0), curvature_ema=0.0, inverse_every=1)
        new, _, _ = jax.jit(method.step, static_argnums=0)(objective, params, method.init(params), batch)
        got = jax.tree.map(lambda a, b: a - b, params, new)  # sgd(1): the step is −direction
    else:
        got, _ = jax.jit(physgrad.methods.Estimator(rule, objective))(params, batch)
    grads = jax.grad(lambda p: jnp.mean(jax.vmap(lambda s: loss(predict(p, s), s))(batch)))(params)
    grad = np.concatenate([np.asarray(grads.weight).reshape(C, -1), np.asarray(grads.bias).reshape(C, 1)], axis=1)
    A, G = _explicit(params, batch, run)
    want = _np_power(A, G, grad, B * STEPS * N, power, damping)
    np.testing.assert_allclose(np.asarray(got.weight).reshape(C, -1), want[:, :-1], rtol=1e-7,
                               atol=1e-9 * np.abs(want).max())  # fmt: skip
    np.testing.assert_allclose(np.asarray(got.bias).ravel(), want[:, -1], rtol=1e-7, atol=1e-9 * np.abs(want).max())


def test_shared_kernel_read_elsewhere_or_computed_differently_is_refused():
    params, batch, predicts, loss, _ = _rollout()
    predict = predicts["loop"]

    def also_summed(p, s):  # the kernel also enters the output directly
        return predict(p, s) + jnp.sum(p.weight)

    def flipped(p, s):  # the second use convolves with the flipped kernel
        conv = lambda w, x: jax.lax.conv_general_dilated(x[None], w, (1,), [(1, 1)])[0]  # noqa: E731
        return jnp.sin(conv(p.weight[:, :, ::-1], conv(p.weight, s["x"])).ravel())

    plan = KroneckerPower().plan
    with pytest.raises(ValueError, match=r"^khig: convolution \d+ \(kernel \(2, 2, 3\)\): parameter leaf 0 is also "
                                         r"used outside its convolutions' kernels; use hig$"):  # fmt: skip
        plan(physgrad.Objective(also_summed, loss), params, batch)
    with pytest.raises(ValueError, match=r"^khig: .*parameter leaf 0 reaches its 2 convolutions as differently "
                                         r"computed kernels; use hig$"):  # fmt: skip
        plan(physgrad.Objective(flipped, loss), params, batch)


def test_inlined_program_computes_the_same_values():
    """``conv_program.inline`` of a reversed scan over inputs, holding a jitted convolution,
    gives the original program's values and leaves no scan or nested call around the convolutions."""
    from physgrad.loops import primitives
    from physgrad.methods import conv_program

    w = jax.random.normal(jax.random.key(41), (C, C, 3), jnp.float64)
    xs = jax.random.normal(jax.random.key(42), (4, C, N), jnp.float64)
    conv = jax.jit(lambda w, x: jax.lax.conv_general_dilated(x[None], w, (1,), [(1, 1)])[0])

    def program(w, xs):
        carry, ys = jax.lax.scan(lambda h, x: (jnp.tanh(conv(w, h) + x), jnp.sum(h)), xs[0], xs, reverse=True)
        return carry, ys

    closed = jax.make_jaxpr(program)(w, xs)
    flat = jax.make_jaxpr(lambda *a: conv_program.inline(closed.jaxpr, closed.consts, a))(w, xs)
    assert [e.primitive.name for e in flat.jaxpr.eqns].count("conv_general_dilated") == 4
    assert "scan" not in [e.primitive.name for e in flat.jaxpr.eqns]
    assert "conv_general_dilated" not in [
        n for e in flat.jaxpr.eqns if e.params for n in _nested_primitives(e, primitives)
    ]
    for a, b in zip(program(w, xs), jax.core.eval_jaxpr(flat.jaxpr, flat.consts, w, xs)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-13)


def _nested_primitives(eqn, primitives):
    """The primitives nested in one equation's parameters (its bodies)."""
    for value in eqn.params.values():
        inner = getattr(value, "jaxpr", value)
        if hasattr(inner, "eqns"):
            yield from primitives(inner)

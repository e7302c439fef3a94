"""KHIG on convolution layers: the KFC factors (``physgrad.methods.conv_factors``) against references.

References: the input patches written out by hand in NumPy (padding by ``numpy.pad``, zero
or circular, strides and dilation by explicit loops), checked against ``jax.jacfwd``'s
Jacobian of the network output with respect to the kernel (``J_K = Σ_t D_t ⊗ p_tᵀ``); the
signals ``D_t`` from ``jax.jacfwd`` of the simulator output with respect to the convolution's
output; where the factorisation is exact (one convolution with one output position, linear
physics shared by all samples) the NumPy float64 HIG formula and ``physgrad.hig``; off that
case the power of the explicit Kronecker matrix ``kron(G, A)/(b T)`` (``numpy.linalg.eigh``)
applied to the gradient from ``jax.grad``.
"""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad import routes
from physgrad.methods import KroneckerPower
from physgrad.methods import conv_factors as kfc
from physgrad.nets import standardised_weight

B, DY = 3, 5


def _np_patches(x, k, stride, pad, dilation, mode):
    """(T, C·∏k) patches of x (C, *S), channel-major, output positions row-major."""
    d = x.ndim - 1
    x = np.pad(x, [(0, 0)] + [(pad, pad)] * d, mode=mode)
    out = [(x.shape[1 + a] - dilation * (k - 1) - 1) // stride + 1 for a in range(d)]
    rows = []
    for t in itertools.product(*(range(n) for n in out)):
        window = x[(slice(None),) + tuple(slice(s * stride, s * stride + dilation * (k - 1) + 1, dilation) for s in t)]
        rows.append(window.ravel())
    return np.stack(rows)


# (name, layer, input shape, the layer's patches: (k, stride, pad, dilation, numpy mode), circular pre-pad)
CASES = {
    "1d-zero-stride2": (lambda k: eqx.nn.Conv1d(2, 3, 3, stride=2, padding=1, key=k), (2, 9), (3, 2, 1, 1, "constant")),
    "1d-circular": (lambda k: eqx.nn.Conv(1, 2, 3, 3, padding="SAME", padding_mode="CIRCULAR", key=k), (2, 8),
                    (3, 1, 1, 1, "wrap")),
    "2d-zero-stride2-dilated": (lambda k: eqx.nn.Conv2d(2, 3, 3, stride=2, padding=2, dilation=2, key=k), (2, 7, 7),
                                (3, 2, 2, 2, "constant")),
}  # fmt: skip


def _problem(layer, shape, prepad=0, seed=0):
    """One convolution through nonlinear physics y = sin(M tanh(z)) (M: DY × O·T), float64."""
    keys = jax.random.split(jax.random.key(seed), 3)
    layer = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, layer)
    params, static = eqx.partition(layer, eqx.is_inexact_array)
    batch = {"x": jax.random.normal(keys[0], (B, *shape), jnp.float64)}

    def conv(p, x):
        if prepad:  # the U-Net's circular padding: jnp.pad(mode="wrap") before a conv without padding
            x = jnp.pad(x, [(0, 0)] + [(prepad, prepad)] * (x.ndim - 1), mode="wrap")
        return eqx.combine(p, static)(x)

    z_size = jax.eval_shape(conv, params, batch["x"][0]).size
    M = jax.random.normal(keys[1], (DY, z_size), jnp.float64) / np.sqrt(z_size)

    def physics(z):
        return jnp.sin(M @ jnp.tanh(z).ravel())

    return params, batch, conv, physics


def _explicit(params, batch, conv, physics, patch_args, prepad=0):
    """A and G from NumPy patches and jacfwd signals; and the check J_K = Σ_t D_t ⊗ p_tᵀ."""
    k, stride, pad, dilation, mode = patch_args

    @jax.jit
    def jacobians(params, xs):
        def one(x):
            with_kernel = lambda w: physics(conv(eqx.tree_at(lambda m: m.weight, params, w), x))  # noqa: E731
            return conv(params, x), jax.jacfwd(physics)(conv(params, x)), jax.jacfwd(with_kernel)(params.weight)

        return jax.vmap(one)(xs)

    zs, Ds, J_Ks = (np.asarray(a) for a in jacobians(params, batch["x"]))
    A = G = 0.0
    for x, z, D, J_K in zip(np.asarray(batch["x"]), zs, Ds, J_Ks):
        wrapped = np.pad(x, [(0, 0)] + [(prepad, prepad)] * (x.ndim - 1), mode="wrap") if prepad else x
        p = _np_patches(wrapped, k, stride, pad, dilation, mode)
        D = D.reshape(DY, z.shape[0], -1)  # (dy, O, T)
        np.testing.assert_allclose(np.einsum("rot,tf->rof", D, p), J_K.reshape(DY, D.shape[1], -1), atol=1e-12)
        p_bar = np.concatenate([p, np.ones((p.shape[0], 1))], axis=1)
        A = A + p_bar.T @ p_bar
        G = G + np.einsum("rot,rqt->oq", D, D)
    return A, G


@pytest.mark.parametrize("name", sorted(CASES))
def test_conv_factors_equal_explicit_patch_sums(name):
    make, shape, patch_args = CASES[name]
    params, batch, conv, physics = _problem(make(jax.random.key(1)), shape)
    (found,) = jax.jit(lambda p, b: kfc.conv_layer_factors(lambda p, s: physics(conv(p, s["x"])), p, b))(params, batch)
    A, G = _explicit(params, batch, conv, physics, patch_args)
    assert (int(found.kernel), int(found.bias)) == (0, 1)  # leaves: weight, bias
    np.testing.assert_allclose(np.asarray(found.A), A, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(found.G), G, rtol=1e-10, atol=1e-12)


def test_conv_factors_of_the_unets_circular_convolution_2d():
    """physgrad.nets' U-Net pads with jnp.pad(mode="wrap") and convolves without padding."""
    params, batch, conv, physics = _problem(eqx.nn.Conv2d(2, 3, 3, key=jax.random.key(2)), (2, 6, 6), prepad=1)
    (found,) = jax.jit(lambda p, b: kfc.conv_layer_factors(lambda p, s: physics(conv(p, s["x"])), p, b))(params, batch)
    A, G = _explicit(params, batch, conv, physics, (3, 1, 0, 1, "constant"), prepad=1)
    assert found.count == B * 36
    np.testing.assert_allclose(np.asarray(found.A), A, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(found.G), G, rtol=1e-10, atol=1e-12)


def test_transposed_convolution_patches_rebuild_the_kernel_jacobian():
    """ConvTranspose (input dilation): Σ_t D_t ⊗ p_tᵀ from the rule's own patches and signals
    equals jacfwd's kernel Jacobian, and G equals the jacfwd signals' sum."""
    layer = eqx.nn.ConvTranspose1d(2, 3, 3, stride=2, padding=1, key=jax.random.key(4))
    params, batch, conv, physics = _problem(layer, (2, 5))
    predict = lambda p, s: physics(conv(p, s["x"]))  # noqa: E731
    structure = routes.JointJacobian.of(physgrad.Objective(predict), params, batch).structure
    (use,) = kfc.find_convolutions(structure)
    no_loss = lambda y: (jnp.zeros(()), jnp.zeros((y.size,)))  # noqa: E731

    @jax.jit
    def computed(params, batch):
        sig, *_ = kfc.layer_signals(structure, (), (use,), params, batch, no_loss, 0)
        p = kfc.conv_patches(structure, use, sig.x[0]).reshape(B, -1, use.d_in)
        D = kfc.conv_signals(structure, use, sig.d_v[0])  # (rows, b, T, O)
        rows = jnp.einsum("rito,itf->irof", D, p)
        rebuilt = jax.vmap(jax.vmap(lambda r: kfc.kernel_matrix(structure, use, r)))(rows)
        J_K = jax.vmap(jax.jacfwd(lambda w, x: physics(conv(eqx.tree_at(lambda m: m.weight, params, w), x))),
                       in_axes=(None, 0))(params.weight, batch["x"])  # fmt: skip
        zs = jax.vmap(conv, in_axes=(None, 0))(params, batch["x"])
        return rebuilt, J_K, jax.vmap(jax.jacfwd(physics))(zs), kfc.conv_layer_factors(predict, params, batch)[0]

    rebuilt, J_K, Ds, found = computed(params, batch)
    np.testing.assert_allclose(np.asarray(rebuilt), np.asarray(J_K), atol=1e-12)
    Ds = np.asarray(Ds).reshape(B, DY, 3, -1)
    np.testing.assert_allclose(np.asarray(found.G), np.einsum("irot,irqt->oq", Ds, Ds), rtol=1e-10)


def _np_hig(J, g, kappa=-0.5, tau=1e-6):
    u, s, vt = np.linalg.svd(J, full_matrices=False)
    keep = s > tau * s.max()
    return vt[keep].T @ (s[keep] ** kappa * (u[:, keep].T @ g))


def test_one_output_position_equals_hig_where_the_factorisation_is_exact():
    """A Conv1d whose output has one position (input length = kernel) and linear physics shared
    by the samples: the block is exactly (1/b) G ⊗ A and KHIG (damping 0) is HIG."""
    layer = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a,
                         eqx.nn.Conv1d(2, 3, 3, key=jax.random.key(5)))  # fmt: skip
    params, static = eqx.partition(layer, eqx.is_inexact_array)
    keys = jax.random.split(jax.random.key(6), 3)
    M = jax.random.normal(keys[0], (4, 3), jnp.float64)
    batch = {"x": jax.random.normal(keys[1], (5, 2, 3), jnp.float64), "t": jax.random.normal(keys[2], (5, 4))}

    def predict(p, s):
        return M @ eqx.combine(p, static)(s["x"]).ravel()

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    got, stats = jax.jit(physgrad.kronecker_hig(predict, loss, damping=0.0))(params, batch)
    hig, hig_stats = jax.jit(physgrad.hig(predict, loss, route=routes.SVD()))(params, batch)
    x, t, Mn = (np.asarray(a) for a in (batch["x"], batch["t"], M))
    a_bar = np.concatenate([x.reshape(5, -1), np.ones((5, 1))], axis=1)  # channel-major patch and the bias's 1
    J = np.concatenate([np.kron(Mn, a_bar[i][None, :]) for i in range(5)])
    W = np.concatenate([np.asarray(params.weight).reshape(3, -1), np.asarray(params.bias).reshape(3, 1)], axis=1)
    g = (2.0 * ((a_bar @ W.T) @ Mn.T - t) / 5).ravel()
    want = _np_hig(J, g).reshape(3, -1)
    np.testing.assert_allclose(np.asarray(got.weight).reshape(3, -1), want[:, :-1], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(got.bias).ravel(), want[:, -1], rtol=1e-9, atol=1e-12)
    for a, h in zip(jax.tree.leaves(got), jax.tree.leaves(hig)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(h), rtol=1e-9, atol=1e-12)
    assert int(stats["rank"]) == int(hig_stats["rank"])


def _two_layer(standardise=False):
    """conv1 (circular, 1-D, 3→3) → tanh → conv2 (zero padding, stride 2, 3→3) → sin(M ·)."""
    keys = jax.random.split(jax.random.key(7), 5)
    c1 = eqx.nn.Conv(1, 3, 3, 3, padding="SAME", padding_mode="CIRCULAR", key=keys[0], dtype=jnp.float64)
    c2 = eqx.nn.Conv1d(3, 3, 3, stride=2, padding=1, key=keys[1], dtype=jnp.float64)
    params = {"c1": c1, "c2": c2}
    params, static = eqx.partition(params, eqx.is_inexact_array)
    M = jax.random.normal(keys[2], (DY, 12), jnp.float64) / 3
    batch = {"x": jax.random.normal(keys[3], (B, 3, 8), jnp.float64), "t": jax.random.normal(keys[4], (B, DY))}

    def first(p, x):
        c1 = eqx.combine(p, static)["c1"]
        if standardise:
            c1 = eqx.tree_at(lambda m: m.weight, c1, standardised_weight(c1.weight))
        return c1(x)

    def second(p, h):
        return eqx.combine(p, static)["c2"](h)

    def predict(p, s):
        return jnp.sin(M @ second(p, jnp.tanh(first(p, s["x"]))).ravel())

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    def plain_first(p, x):  # conv1 with p's kernel as it is (the standardised one passed in)
        return eqx.combine(p, static)["c1"](x)

    return params, batch, predict, loss, plain_first, second, M


def _np_power(A, G, grad, count, power, damping):
    lam, q = np.linalg.eigh(np.kron(G, A) / count)
    phi = (np.maximum(lam, 0) + damping * lam.max()) ** power
    return (q @ (phi * (q.T @ grad.ravel()))).reshape(grad.shape)


@pytest.mark.costly("the only check of KHIG's conv directions, and of a reparametrised kernel, against a reference")
@pytest.mark.parametrize("standardise", [False, True])
def test_each_conv_layer_gets_the_power_of_its_kfc_block(standardise):
    """Two conv layers through nonlinear physics: each layer's ΔK̄ = φ(kron(G, A)/(bT)) vec(∇K̄)
    with G, A from jacfwd signals and NumPy patches and ∇K̄ from jax.grad; a standardised
    kernel's direction is (∂f/∂θ)ᵀ ΔK (jax.vjp of nets.standardised_weight)."""
    params, batch, predict, loss, plain_first, second, M = _two_layer(standardise)
    power, damping = -0.75, 1e-3
    got, _ = jax.jit(physgrad.methods.Estimator(KroneckerPower(power, 0.0, damping, eigh_batched=False),
                                                physgrad.Objective(predict, loss)))(params, batch)  # fmt: skip
    batched, _ = jax.jit(physgrad.methods.Estimator(KroneckerPower(power, 0.0, damping, eigh_batched=True),
                                                    physgrad.Objective(predict, loss)))(params, batch)  # fmt: skip
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(batched)):  # one eigh per size = one per factor
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-14)

    kernel1 = standardised_weight(params["c1"].weight) if standardise else params["c1"].weight
    with_k1 = {**params, "c1": eqx.tree_at(lambda m: m.weight, params["c1"], kernel1)}

    @jax.jit
    def pieces(p):
        def batch_loss(k1, w2, b1, b2):
            q = {"c1": eqx.tree_at(lambda m: (m.weight, m.bias), p["c1"], (k1, b1)),
                 "c2": eqx.tree_at(lambda m: (m.weight, m.bias), p["c2"], (w2, b2))}  # fmt: skip
            ys = jax.vmap(lambda s: jnp.sin(M @ second(q, jnp.tanh(plain_first(q, s["x"]))).ravel()))(batch)
            return jnp.mean(jax.vmap(loss)(ys, batch))

        grads = jax.grad(batch_loss, argnums=(0, 1, 2, 3))(p["c1"].weight, p["c2"].weight, p["c1"].bias, p["c2"].bias)
        z1 = jax.vmap(lambda x: plain_first(p, x))(batch["x"])
        h = jnp.tanh(z1)
        z2 = jax.vmap(lambda x: second(p, x))(h)
        D1 = jax.vmap(jax.jacfwd(lambda z: jnp.sin(M @ second(p, jnp.tanh(z)).ravel())))(z1)
        D2 = jax.vmap(jax.jacfwd(lambda z: jnp.sin(M @ z.ravel())))(z2)
        return grads, h, D1, D2

    grads, h, D1, D2 = (jax.tree.map(np.asarray, a) for a in pieces(with_k1))
    x = np.asarray(batch["x"])
    layers = [(x, D1, (3, 1, 1, 1, "wrap"), grads[0], grads[2]), (h, D2, (3, 2, 1, 1, "constant"), grads[1], grads[3])]
    for (inputs, D, args, g_w, g_b), name in zip(layers, ("c1", "c2")):
        P = [np.concatenate([(p := _np_patches(a, *args)), np.ones((p.shape[0], 1))], axis=1) for a in inputs]
        Ds = [d.reshape(DY, 3, -1) for d in D]
        A = sum(p.T @ p for p in P)
        G = sum(np.einsum("rot,rqt->oq", d, d) for d in Ds)
        grad = np.concatenate([g_w.reshape(3, -1), g_b.reshape(3, 1)], axis=1)
        want = _np_power(A, G, grad, B * P[0].shape[0], power, damping)
        delta_k = want[:, :-1].reshape(g_w.shape)
        if name == "c1" and standardise:
            _, pull = jax.vjp(standardised_weight, params["c1"].weight)
            delta_k = np.asarray(pull(jnp.asarray(delta_k))[0])
        np.testing.assert_allclose(np.asarray(got[name].weight), delta_k, rtol=1e-7, atol=1e-9 * np.abs(delta_k).max())
        np.testing.assert_allclose(np.asarray(got[name].bias).ravel(), want[:, -1], rtol=1e-7,
                                   atol=1e-9 * np.abs(want).max())  # fmt: skip


def test_probes_estimate_g_without_bias_and_draw_anew_per_batch():
    """G from s Rademacher probes per sample averages to the exact G (relative error ~ √(2/s))."""
    make, shape, _ = CASES["1d-circular"]
    params, batch, conv, physics = _problem(make(jax.random.key(1)), shape)
    predict = lambda p, s: physics(conv(p, s["x"]))  # noqa: E731
    factors = jax.jit(lambda p, b, s: kfc.conv_layer_factors(predict, p, b, probes=s)[0], static_argnums=2)
    exact, sampled = factors(params, batch, 0), factors(params, batch, 4000)
    np.testing.assert_allclose(np.asarray(sampled.A), np.asarray(exact.A), rtol=1e-12)
    error = np.linalg.norm(np.asarray(sampled.G) - np.asarray(exact.G)) / np.linalg.norm(np.asarray(exact.G))
    assert error < 0.1, error
    other = {"x": batch["x"][::-1]}  # the same samples in another order: other probes
    assert not np.allclose(np.asarray(factors(params, other, 2).G), np.asarray(factors(params, batch, 2).G))
    with pytest.raises(ValueError, match=r"^probes must be >= 0 \(0: every output row\), got -1$"):
        KroneckerPower(probes=-1)


# CPU sizes of the shipped U-Net problems (tests/test_problems.py's small data)
UNET_SMALL = {
    "poisson": {"resolution": "16", "levels": "2", "filters": "4", "n_train": "16", "n_test": "8"},
    "heat": {"resolution": "16", "levels": "2", "filters": "4", "n_train": "16", "n_test": "8"},
    "navier_stokes": {"resolution": "16", "size": "32.0", "box": "14.0", "swirl_sigma": "5.0", "falloff": "20.0",
                      "levels": "3", "filters": "4", "n_train": "16", "n_test": "8"},
}  # fmt: skip


@pytest.mark.slow  # minutes of compilation on a shared CPU; the directions are checked by the tests above
@pytest.mark.parametrize("problem", sorted(UNET_SMALL))
def test_khig_trains_the_unet_problems(problem, tmp_path):
    """8 steps of khig (KFC factors, G from 4 probes) lower the test loss on each U-Net problem."""
    from cli_training import cli_test_losses

    settings = {**UNET_SMALL[problem], "batch_size": "8", "eval_every": "4", "probes": "4", "lr": "0.01",
                "damping": "0.01"}  # fmt: skip
    test = cli_test_losses(tmp_path / "run", problem, "khig", 8, settings)
    assert len(test) == 3 and all(np.isfinite(test)), test
    assert test[-1] < test[0], test

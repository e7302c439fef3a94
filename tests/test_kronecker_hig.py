"""Kronecker-factored HIG (``physgrad.kronecker_hig``, method ``khig``) against independent references.

References: where the Gauss–Newton block is exactly Kronecker (one dense layer, linear
physics shared by all samples) the NumPy float64 HIG formula ``V Σ^{−½} Uᵀ g`` from the
SVD of the explicit Jacobian (built in NumPy as ``M ⊗ ā_iᵀ`` per sample) and
``physgrad.hig``'s own direction; off that case, the factors' definitions from ``jax.jacfwd``
Jacobians written out by hand for a 2-layer tanh MLP through a nonlinear simulator, and the
power of the explicit Kronecker matrix ``kron(G, A)/b`` (``numpy.linalg.eigh``) applied to
the gradient from ``jax.grad``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from cli_training import cli_test_losses
from physgrad import routes
from physgrad.harness.registry import METHODS, PROBLEMS, describe, paper_defaults
from physgrad.methods.kronecker_hig import layer_factors


def _linear_problem(d_in, d_out, dy, b, bias, transposed, dtype, seed=0):
    keys = jax.random.split(jax.random.key(seed), 5)
    shape = (d_in, d_out) if transposed else (d_out, d_in)
    params = {"W": jax.random.normal(keys[0], shape, dtype) / float(np.sqrt(d_in))}
    if bias:
        params["c"] = jax.random.normal(keys[1], (d_out,), dtype)
    M = jax.random.normal(keys[2], (dy, d_out), dtype)  # linear physics, the same for every sample
    batch = {"x": jax.random.normal(keys[3], (b, d_in), dtype), "t": jax.random.normal(keys[4], (b, dy), dtype)}

    def predict(p, s):
        z = s["x"] @ p["W"] if transposed else p["W"] @ s["x"]
        return M @ (z + p["c"] if bias else z)

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    return params, batch, predict, loss, M


def _numpy_hig(params, batch, M, bias, transposed, kappa=-0.5, tau=1e-6):
    """V Σ^κ Uᵀ g from NumPy's SVD of the explicit J (rows: sample-major; columns: W̄ = [W c] row-major)."""
    W = np.asarray(params["W"], np.float64)
    W = W.T if transposed else W
    c = np.asarray(params["c"], np.float64) if bias else np.zeros(W.shape[0])
    M, x, t = (np.asarray(a, np.float64) for a in (M, batch["x"], batch["t"]))
    b = x.shape[0]
    a_bar = np.concatenate([x, np.ones((b, 1))], axis=1) if bias else x
    J = np.concatenate([np.kron(M, a_bar[i][None, :]) for i in range(b)])
    y = (x @ W.T + c) @ M.T
    g = (2.0 * (y - t) / b).ravel()
    u, s, vt = np.linalg.svd(J, full_matrices=False)
    keep = s > tau * s.max()
    flat = vt[keep].T @ (s[keep] ** kappa * (u[:, keep].T @ g))
    d = flat.reshape(W.shape[0], -1)
    out = {"W": d[:, : W.shape[1]].T if transposed else d[:, : W.shape[1]]}
    if bias:
        out["c"] = d[:, -1]
    return out


def _relative(got, want):
    got = np.concatenate([np.asarray(got[k], np.float64).ravel() for k in sorted(want)])
    want = np.concatenate([np.asarray(want[k], np.float64).ravel() for k in sorted(want)])
    return np.linalg.norm(got - want) / np.linalg.norm(want)


# (d_in, d_out, dim y, batch, transposed): tall and wide J, a batch smaller than d_in
# (A rank-deficient), physics with fewer outputs than the layer (G rank-deficient), x @ W.
SHAPES = [(5, 4, 3, 7, False), (3, 6, 8, 2, False), (8, 3, 2, 16, True), (6, 6, 6, 5, False)]


@pytest.mark.parametrize("bias", [True, False])
@pytest.mark.parametrize("shape", SHAPES)
def test_equals_hig_where_the_factorisation_is_exact_float64(shape, bias):
    d_in, d_out, dy, b, transposed = shape
    params, batch, predict, loss, M = _linear_problem(d_in, d_out, dy, b, bias, transposed, jnp.float64)
    got, stats = jax.jit(physgrad.kronecker_hig(predict, loss, damping=0.0))(params, batch)
    want = _numpy_hig(params, batch, M, bias, transposed)
    assert _relative(got, want) < 1e-9
    assert all(got[k].dtype == jnp.float64 for k in got)
    if not bias or shape not in (SHAPES[0], SHAPES[3]):  # the NumPy formula covers these (compile time)
        return
    hig, hig_stats = jax.jit(physgrad.hig(predict, loss, route=routes.SVD()))(params, batch)
    assert _relative(got, hig) < 1e-9
    assert int(stats["rank"]) == int(hig_stats["rank"])
    assert float(stats["sigma_max"]) == pytest.approx(float(hig_stats["sigma_max"]), rel=1e-9)
    assert float(stats["loss"]) == pytest.approx(float(hig_stats["loss"]), rel=1e-12)


@pytest.mark.parametrize("bias", [True, False])
@pytest.mark.parametrize("shape", SHAPES[:2])
def test_equals_hig_where_the_factorisation_is_exact_float32(shape, bias):
    d_in, d_out, dy, b, transposed = shape
    params, batch, predict, loss, M = _linear_problem(d_in, d_out, dy, b, bias, transposed, jnp.float32)
    got, _ = jax.jit(physgrad.kronecker_hig(predict, loss, damping=0.0))(params, batch)
    assert all(got[k].dtype == jnp.float32 for k in got)
    assert _relative(got, _numpy_hig(params, batch, M, bias, transposed)) < 1e-4
    if bias and shape == SHAPES[0]:
        hig, _ = jax.jit(physgrad.hig(predict, loss))(params, batch)
        assert _relative(got, hig) < 1e-4


def test_equinox_linear_layer_and_power_minus_one_is_gauss_newton_when_exact():
    """eqx.nn.Linear as the parameters (a whole module); p = −1 is the exact pseudo-inverse step."""
    layer = eqx.nn.Linear(4, 3, key=jax.random.key(1), dtype=jnp.float64)
    M = jax.random.normal(jax.random.key(2), (5, 3), jnp.float64)
    batch = {"x": jax.random.normal(jax.random.key(3), (6, 4), jnp.float64),
             "t": jax.random.normal(jax.random.key(4), (6, 5), jnp.float64)}  # fmt: skip

    def predict(model, s):
        return M @ model(s["x"])

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    got, _ = eqx.filter_jit(physgrad.kronecker_hig(predict, loss, power=-1.0, damping=0.0))(layer, batch)
    want = _numpy_hig({"W": layer.weight, "c": layer.bias}, batch, M, True, False, kappa=-1.0)
    assert _relative({"W": got.weight, "c": got.bias}, want) < 1e-9


# --- off the exact case: a nonlinear 2-layer MLP through a nonlinear simulator -------------
D_IN, HIDDEN, D_OUT, DIM_Y, BATCH = 3, 5, 4, 6, 9


def _mlp_problem():
    keys = jax.random.split(jax.random.key(7), 6)
    params = {
        "l1": {"W": jax.random.normal(keys[0], (HIDDEN, D_IN)) / 2, "b": jax.random.normal(keys[1], (HIDDEN,)) / 4},
        "l2": {"W": jax.random.normal(keys[2], (D_OUT, HIDDEN)) / 2, "b": jax.random.normal(keys[3], (D_OUT,)) / 4},
    }
    P = jax.random.normal(keys[4], (DIM_Y, D_OUT)) / 2

    def simulate(x, s):  # nonlinear and sample-dependent physics
        return jnp.sin(P @ x) * (1.0 + s["x"][0] ** 2) + 0.1 * (P @ x) ** 3

    def predict(p, s):
        h = jnp.tanh(p["l1"]["W"] @ s["x"] + p["l1"]["b"])
        return simulate(p["l2"]["W"] @ h + p["l2"]["b"], s)

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2) + 0.1 * jnp.sum(y**4)

    batch = {"x": jax.random.normal(keys[5], (BATCH, D_IN)), "t": jax.random.normal(keys[4], (BATCH, DIM_Y))}
    return params, batch, predict, loss, simulate


def _explicit_factors(params, batch, simulate):
    """[(A, G)] per layer by their definitions: ā_i by hand, D_i = jacfwd of y w.r.t. z_i."""
    W1, b1, W2, b2 = params["l1"]["W"], params["l1"]["b"], params["l2"]["W"], params["l2"]["b"]

    @jax.jit
    @jax.vmap
    def per_sample(s):
        z1 = W1 @ s["x"] + b1
        h = jnp.tanh(z1)
        z2 = W2 @ h + b2
        D1 = jax.jacfwd(lambda z: simulate(W2 @ jnp.tanh(z) + b2, s))(z1)
        D2 = jax.jacfwd(lambda z: simulate(z, s))(z2)
        return h, D1, D2

    h, D1, D2 = (np.asarray(a) for a in per_sample(batch))
    a1 = np.concatenate([np.asarray(batch["x"]), np.ones((BATCH, 1))], axis=1)
    a2 = np.concatenate([h, np.ones((BATCH, 1))], axis=1)
    A1 = sum(np.outer(a1[i], a1[i]) for i in range(BATCH))
    A2 = sum(np.outer(a2[i], a2[i]) for i in range(BATCH))
    G1 = sum(D1[i].T @ D1[i] for i in range(BATCH))
    G2 = sum(D2[i].T @ D2[i] for i in range(BATCH))
    return [(A1, G1), (A2, G2)]


@pytest.fixture(scope="module")
def mlp():
    params, batch, predict, loss, simulate = _mlp_problem()
    return params, batch, predict, loss, _explicit_factors(params, batch, simulate)


def test_factors_equal_their_definitions_on_a_nonlinear_mlp_through_nonlinear_physics(mlp):
    params, batch, predict, _, explicit = mlp
    found = jax.jit(lambda p, b: layer_factors(predict, p, b))(params, batch)
    assert [(int(f.weight), int(f.bias)) for f in found] == [(0, 1), (2, 3)]  # leaves: l1.W, l1.b, l2.W, l2.b
    for f, (A, G) in zip(found, explicit):
        np.testing.assert_allclose(np.asarray(f.A), A, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.asarray(f.G), G, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(("power", "damping"), [(-1.0, 0.0), (-0.75, 0.0), (-0.75, 1e-3), (-0.5, 1e-2)])
def test_each_layer_gets_the_power_of_its_kronecker_block(mlp, power, damping):
    """ΔW̄ = φ(kron(G, A)/b) vec(∇W̄), φ(λ) = (λ + δ λ_max)^p, with NumPy's eigh of the explicit
    Kronecker matrix; p = −1, δ = 0 is Kronecker-factored Gauss–Newton, b G⁻¹ ∇W̄ A⁻¹."""
    params, batch, predict, loss, explicit = mlp
    estimate = physgrad.kronecker_hig(predict, loss, power=power, damping=damping, truncation=0.0)
    got, stats = jax.jit(estimate)(params, batch)
    grad = jax.jit(jax.grad(lambda p: jnp.mean(jax.vmap(lambda s: loss(predict(p, s), s))(batch))))(params)
    for name, (A, G) in zip(("l1", "l2"), explicit):
        full_grad = np.concatenate([np.asarray(grad[name]["W"]), np.asarray(grad[name]["b"])[:, None]], axis=1)
        lam, q = np.linalg.eigh(np.kron(G, A) / BATCH)
        phi = (np.maximum(lam, 0) + damping * lam.max()) ** power
        want = (q @ (phi * (q.T @ full_grad.ravel()))).reshape(full_grad.shape)
        if power == -1.0 and damping == 0.0:
            np.testing.assert_allclose(want, BATCH * np.linalg.inv(G) @ full_grad @ np.linalg.inv(A), rtol=1e-6)
        got_full = np.concatenate([np.asarray(got[name]["W"]), np.asarray(got[name]["b"])[:, None]], axis=1)
        np.testing.assert_allclose(got_full, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())
    assert int(stats["rank"]) == HIDDEN * (D_IN + 1) + D_OUT * (HIDDEN + 1)  # nothing truncated at τ = 0


def test_leftover_parameters_form_one_exact_block_and_grouped_convolutions_are_refused():
    """A weight used twice is no dense layer: its block is (J_oᵀJ_o)^p J_oᵀ g exactly."""
    keys = jax.random.split(jax.random.key(3), 4)
    params = {"W": jax.random.normal(keys[0], (3, 3)) / 2, "shared": jax.random.normal(keys[1], (3, 3)) / 2}
    batch = {"x": jax.random.normal(keys[2], (4, 3)), "t": jax.random.normal(keys[3], (4, 3))}

    def predict(p, s):
        return p["shared"] @ jnp.tanh(p["shared"] @ jnp.tanh(p["W"] @ s["x"]))

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    got, _ = jax.jit(physgrad.kronecker_hig(predict, loss, truncation=0.0, damping=0.0))(params, batch)

    @jax.jit
    def explicit(w):  # J_o of the shared weight and g = ∂L/∂y
        J = jax.vmap(jax.jacrev(lambda w, s: predict({**params, "shared": w}, s)), in_axes=(None, 0))(w, batch)
        y = jax.vmap(lambda s: predict(params, s))(batch)
        return J, jax.grad(lambda y: jnp.mean(jax.vmap(loss)(y, batch)))(y)

    J, g = (np.asarray(a) for a in explicit(params["shared"]))
    J = J.reshape(4 * 3, 9)
    lam, q = np.linalg.eigh(J.T @ J)
    want = q @ (lam**-0.75 * (q.T @ (J.T @ g.ravel())))
    np.testing.assert_allclose(np.asarray(got["shared"]).ravel(), want, rtol=1e-6)

    with pytest.raises(ValueError, match=r"^khig: 9 parameters are outside .* explicit_max=4; use hig") as info:
        physgrad.kronecker_hig(predict, loss, explicit_max=4)(params, batch)
    assert "\n" not in str(info.value)

    # convolutions have KFC factors (tests/test_kronecker_conv.py); grouped ones are refused
    conv = eqx.nn.Conv1d(2, 2, 3, groups=2, key=keys[0])
    with pytest.raises(ValueError, match=r"^khig: convolution \d+ \(kernel \(2, 1, 3\)\) is grouped; .*; use hig$"):
        physgrad.kronecker_hig(lambda m, s: m(s["x"][:2, None]).ravel(), lambda y, s: jnp.sum(y**2))(conv, batch)


def test_khig_is_registered_with_hig_defaults_and_trains_oscillators_from_the_cli(tmp_path):
    assert "khig" in METHODS and describe("khig").startswith("Kronecker-factored HIG")
    assert paper_defaults(PROBLEMS["oscillators"], "khig") == paper_defaults(PROBLEMS["oscillators"], "hig")
    settings = {"n_train": "64", "n_test": "64", "batch_size": "16", "eval_every": "8"}
    test = cli_test_losses(tmp_path / "run", "oscillators", "khig", 16, settings)
    assert len(test) == 3 and all(np.isfinite(test))
    assert test[0] > test[1] > test[2], test


# --- running averages of the factors (K-FAC's way): AveragedKronecker ------------------------
def _second_batch(batch):
    keys = jax.random.split(jax.random.key(11), 2)
    return {"x": jax.random.normal(keys[0], batch["x"].shape), "t": jax.random.normal(keys[1], batch["t"].shape)}


def _power_of(A, G, grad_full, power, damping, b):
    """φ(kron(G, A)/b) vec(∇W̄) with NumPy's eigh of the explicit Kronecker matrix."""
    lam, q = np.linalg.eigh(np.kron(G, A) / b)
    phi = (np.maximum(lam, 0) + damping * lam.max()) ** power
    return (q @ (phi * (q.T @ grad_full.ravel()))).reshape(grad_full.shape)


def _full(tree, name):
    return np.concatenate([np.asarray(tree[name]["W"]), np.asarray(tree[name]["b"])[:, None]], axis=1)


def test_averaged_factors_without_averaging_equal_the_fresh_rule(mlp):
    import optax

    params, batch, predict, loss, _ = mlp
    objective = physgrad.Objective(predict, loss)
    rule = physgrad.methods.KroneckerPower(-0.75, 1e-6, 1e-4)
    fresh = physgrad.Method(rule, optax.sgd(0.05))
    averaged = physgrad.methods.AveragedKronecker(rule, optax.sgd(0.05), curvature_ema=0.0, inverse_every=1)
    p_f, s_f, p_a, s_a = params, fresh.init(params), params, averaged.init(params)
    fresh_step = jax.jit(fresh.step, static_argnums=0)  # once: both steps run one program each
    averaged_step = jax.jit(averaged.step, static_argnums=0)
    for b in (batch, _second_batch(batch)):
        p_f, s_f, _ = fresh_step(objective, p_f, s_f, b)
        p_a, s_a, stats = averaged_step(objective, p_a, s_a, b)
        assert int(stats["refreshed"]) == 1
    for a, f in zip(jax.tree.leaves(p_a), jax.tree.leaves(p_f)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(f), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("inverse_every", [1, 2])
def test_running_factors_and_their_refresh_period(mlp, inverse_every):
    """Second step: G = β G(θ₀, b₁) + (1 − β) G(θ₁, b₂) (A likewise) in the state; the direction
    is the power of that average (k = 1) or of the first step's factors (k = 2: not refreshed),
    applied to this batch's gradient; checked with NumPy's eigh of the explicit kron(G, A)."""
    import optax

    params, batch, predict, loss, _ = mlp
    beta, lr, damping = 0.6, 0.05, 1e-3
    objective = physgrad.Objective(predict, loss)
    rule = physgrad.methods.KroneckerPower(-0.75, 0.0, damping)
    method = physgrad.methods.AveragedKronecker(rule, optax.sgd(lr), curvature_ema=beta, inverse_every=inverse_every)
    step = jax.jit(method.step, static_argnums=0)
    second = _second_batch(batch)
    p1, state, _ = step(objective, params, method.init(params), batch)
    p2, state, stats = step(objective, p1, state, second)
    assert int(stats["refreshed"]) == (inverse_every == 1)

    factors = jax.jit(lambda p, b: layer_factors(predict, p, b))
    first, now = factors(params, batch), factors(p1, second)
    grad = jax.jit(jax.grad(lambda p: jnp.mean(jax.vmap(lambda s: loss(predict(p, s), s))(second))))(p1)
    for k, name in enumerate(("l1", "l2")):
        A = beta * np.asarray(first[k].A) + (1 - beta) * np.asarray(now[k].A)
        G = beta * np.asarray(first[k].G) + (1 - beta) * np.asarray(now[k].G)
        left, right = state.control.factors[2 * k]  # leaf 2k: the layer's W (d_out × d_in): G left, A right
        np.testing.assert_allclose(np.asarray(left)[: G.shape[0], : G.shape[0]], G, rtol=1e-10)
        np.testing.assert_allclose(np.asarray(right)[: A.shape[0], : A.shape[0]], A, rtol=1e-10)
        used = (A, G) if inverse_every == 1 else (np.asarray(first[k].A), np.asarray(first[k].G))
        want = _power_of(*used, _full(grad, name), -0.75, damping, BATCH)
        got = (_full(p1, name) - _full(p2, name)) / lr
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())


@pytest.mark.slow  # ~8 s of compilation: the fast tier's budget is tight
def test_running_factors_of_a_transposed_layer_without_bias():
    """``x @ W`` (W stored d_in × d_out) keeps A in the left factor and G in the right one."""
    import optax

    keys = jax.random.split(jax.random.key(5), 4)
    params = {"W1": jax.random.normal(keys[0], (3, 4)) / 2, "W2": jax.random.normal(keys[1], (2, 4)) / 2}
    batch = {"x": jax.random.normal(keys[2], (6, 3)), "t": jax.random.normal(keys[3], (6, 2))}

    def predict(p, s):
        return jnp.sin(p["W2"] @ jnp.tanh(s["x"] @ p["W1"]))

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    objective = physgrad.Objective(predict, loss)
    rule = physgrad.methods.KroneckerPower(-0.75, 1e-6, 1e-4)
    fresh, averaged = (
        physgrad.Method(rule, optax.sgd(0.1)),
        physgrad.methods.AveragedKronecker(rule, optax.sgd(0.1), 0.0, 1),
    )
    p_f, _, _ = jax.jit(fresh.step, static_argnums=0)(objective, params, fresh.init(params), batch)
    p_a, state, _ = jax.jit(averaged.step, static_argnums=0)(objective, params, averaged.init(params), batch)
    for name in ("W1", "W2"):
        np.testing.assert_allclose(np.asarray(p_a[name]), np.asarray(p_f[name]), rtol=1e-10)
    (f1,) = [f for f in layer_factors(predict, params, batch) if f.weight == 0]
    left, right = state.control.factors[0]  # W1 (3 × 4) as x @ W1: A (3 × 3, no bias) left, G (4 × 4) right
    np.testing.assert_allclose(np.asarray(left)[:3, :3], np.asarray(f1.A), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(right)[:4, :4], np.asarray(f1.G), rtol=1e-10)
    assert not np.any(np.asarray(left)[3]) and not np.any(np.asarray(right)[4])  # the unused bias slots


def test_khig_running_averages_from_the_registry():
    method = METHODS["khig"](curvature_ema=0.95, inverse_every=5)
    assert isinstance(method, physgrad.methods.AveragedKronecker)
    assert (method.curvature_ema, method.inverse_every) == (0.95, 5)
    assert isinstance(METHODS["khig"](), physgrad.Method)  # fresh factors by default (HIG's way)
    with pytest.raises(ValueError, match=r"^curvature_ema must be in \[0, 1\), got 1.0$"):
        METHODS["khig"](curvature_ema=1.0)


def test_the_power_ablation_arms_are_khig_at_their_power():
    # kgn and khig_half exist so that one bench ranks the three powers side by side: each is
    # khig with its power fixed, the same other settings, HIG's defaults and khig's search space.
    from physgrad.harness.registry import hyperparameters
    from physgrad.harness.spaces import space_of

    settings = {"damping": 1e-3, "probes": 2, "curvature_ema": 0.9, "inverse_every": 4, "curvature_every": 2}
    khig_settings = {k: v for k, v in hyperparameters("khig").items() if k != "power"}
    for name, power in (("kgn", -1.0), ("khig_half", -0.5)):
        assert hyperparameters(name) == khig_settings, name
        assert METHODS[name]().rule == METHODS["khig"](power=power).rule
        arm, reference = METHODS[name](**settings), METHODS["khig"](power=power, **settings)
        assert (arm.rule, arm.curvature_ema, arm.inverse_every, arm.curvature_every) == (
            reference.rule, reference.curvature_ema, reference.inverse_every, reference.curvature_every)  # fmt: skip
        assert paper_defaults(PROBLEMS["quantum_dipole"], name) == paper_defaults(PROBLEMS["quantum_dipole"], "hig")
        assert space_of(name) == space_of("khig")

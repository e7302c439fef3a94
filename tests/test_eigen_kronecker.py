"""Eigenvalue-corrected KHIG (``EigenCorrectedKronecker``, method ``ekhig``) against independent references.

References: KHIG's own direction (``physgrad.kronecker_hig``, itself tested against NumPy's
HIG) where the layer's Gauss–Newton block is exactly Kronecker (one dense layer under linear
physics shared by the samples; one sample through a nonlinear MLP and simulator); off that
case, the diagonal of ``Uᵀ (JᵀJ) U`` with J each layer's Jacobian from ``jax.jacfwd`` and
``U = kron(U_G, U_A)`` formed in NumPy, and the direction ``U φ(Λ) Uᵀ ∇W̄`` from it with the
gradient from ``jax.grad``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
from cli_training import cli_test_losses
from physgrad.harness.registry import METHODS, PROBLEMS, describe, paper_defaults
from physgrad.methods import KroneckerPower
from physgrad.methods.eigen_kronecker import EigenCorrectedKronecker, KeptEigenbasis, layer_corrections
from physgrad.methods.kronecker_hig import layer_factors


def _method(rule, lr=1.0, basis_every=1):
    return EigenCorrectedKronecker(rule, optax.sgd(lr), basis_every=basis_every)  # pyright: ignore[reportCallIssue]  (control is a property)


def _step(method, objective, params, state, batch):
    return jax.jit(method.step, static_argnums=0)(objective, params, state, batch)


def _compiled(pieces, objective, params, batch):
    """``pieces(objective.predict, params, batch)`` (``layer_factors``, ``layer_corrections``)
    compiled as one program: eagerly, each of its operations compiles on its own (3-5x the CPU)."""
    return eqx.filter_jit(lambda p, b: pieces(objective.predict, p, b))(params, batch)


def _leaves_close(a, b, rtol):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=rtol * np.abs(np.asarray(y)).max())


def _linear_problem(transposed):
    keys = jax.random.split(jax.random.key(0), 5)
    d_in, d_out, dy, b = 5, 4, 3, 7
    params = {"W": jax.random.normal(keys[0], (d_in, d_out) if transposed else (d_out, d_in)) / 2,
              "c": jax.random.normal(keys[1], (d_out,))}  # fmt: skip
    M = jax.random.normal(keys[2], (dy, d_out))  # linear physics, the same for every sample
    batch = {"x": jax.random.normal(keys[3], (b, d_in)), "t": jax.random.normal(keys[4], (b, dy))}

    def predict(p, s):
        return M @ ((s["x"] @ p["W"] if transposed else p["W"] @ s["x"]) + p["c"])

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    return params, batch, physgrad.Objective(predict, loss)


# --- a nonlinear 2-layer MLP through a nonlinear, sample-dependent simulator ----------------
D_IN, HIDDEN, D_OUT, DIM_Y, BATCH = 3, 5, 4, 6, 9


def _mlp_problem(batch_size=BATCH):
    keys = jax.random.split(jax.random.key(7), 6)
    params = {
        "l1": {"W": jax.random.normal(keys[0], (HIDDEN, D_IN)) / 2, "b": jax.random.normal(keys[1], (HIDDEN,)) / 4},
        "l2": {"W": jax.random.normal(keys[2], (D_OUT, HIDDEN)) / 2, "b": jax.random.normal(keys[3], (D_OUT,)) / 4},
    }
    P = jax.random.normal(keys[4], (DIM_Y, D_OUT)) / 2

    def predict(p, s):
        h = jnp.tanh(p["l1"]["W"] @ s["x"] + p["l1"]["b"])
        z = P @ (p["l2"]["W"] @ h + p["l2"]["b"])
        return jnp.sin(z) * (1.0 + s["x"][0] ** 2) + 0.1 * z**3

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2) + 0.1 * jnp.sum(y**4)

    batch = {"x": jax.random.normal(keys[5], (batch_size, D_IN)), "t": jax.random.normal(keys[4], (batch_size, DIM_Y))}
    return params, batch, physgrad.Objective(predict, loss)


def _layer_jacobian(objective, params, batch, name):
    """J of one layer (rows b·dim y sample-major; columns W̄ = [W b] row-major) by jacfwd."""

    @jax.jit
    def jac(p):
        def one(s):
            return jax.jacfwd(lambda q: objective.predict({**p, name: q}, s))(p[name])

        return jax.vmap(one)(batch)

    J = jac(params)
    full = np.concatenate([np.asarray(J["W"]), np.asarray(J["b"])[..., None]], axis=-1)  # (b, dim y, d_out, d_in')
    return full.reshape(full.shape[0] * full.shape[1], -1)


def _full(tree, name):
    return np.concatenate([np.asarray(tree[name]["W"]), np.asarray(tree[name]["b"])[:, None]], axis=1)


# --- where the factorisation is exact it is KHIG ------------------------------------------
@pytest.mark.parametrize("transposed", [False, True])
def test_equals_khig_under_linear_physics_shared_by_the_samples(transposed):
    """One dense layer, M the same for all samples: Λ_ij = γ_i α_j / b, the direction is KHIG's
    (and HIG's) with damping 0; ``x @ W`` keeps the bases the other way round."""
    params, batch, objective = _linear_problem(transposed)
    rule = KroneckerPower(-0.75, 1e-6, 0.0)
    corrected = _method(rule)
    got, state, stats = _step(corrected, objective, params, corrected.init(params), batch)
    want, _ = jax.jit(physgrad.kronecker_hig(objective.predict, objective.loss, damping=0.0))(params, batch)
    _leaves_close(jax.tree.map(lambda p, n: p - n, params, got), want, 1e-9)
    assert int(stats["refreshed"]) == 1 and int(stats["rank"]) == 3 * 6  # rank G = dim y = 3, A full rank
    ((_, q_g, q_a, lam),) = _compiled(layer_corrections, objective, params, batch)
    (f,) = _compiled(layer_factors, objective, params, batch)
    products = np.outer(np.linalg.eigvalsh(np.asarray(f.G)), np.linalg.eigvalsh(np.asarray(f.A))) / 7
    np.testing.assert_allclose(np.asarray(lam), products, rtol=1e-9, atol=1e-12 * products.max())
    left, right = state.control.bases[0]
    g_basis, a_basis = (right, left) if transposed else (left, right)
    np.testing.assert_allclose(np.asarray(g_basis)[:4, :4], np.asarray(q_g), atol=1e-12)
    np.testing.assert_allclose(np.asarray(a_basis)[:6, :6], np.asarray(q_a), atol=1e-12)


def test_equals_khig_for_one_sample_through_a_nonlinear_mlp_and_simulator():
    """One sample: each layer's block D_1ᵀD_1 ⊗ ā_1ā_1ᵀ is a Kronecker product (rank-1 A), so
    the corrected eigenvalues are the products γα and the directions agree, damping included."""
    params, batch, objective = _mlp_problem(batch_size=1)
    rule = KroneckerPower(-0.75, 1e-6, 1e-3)
    corrected = _method(rule)
    got, _, stats = _step(corrected, objective, params, corrected.init(params), batch)
    want, want_stats = jax.jit(physgrad.kronecker_hig(objective.predict, objective.loss, damping=1e-3))(params, batch)
    _leaves_close(jax.tree.map(lambda p, n: p - n, params, got), want, 1e-8)
    assert int(stats["rank"]) == int(want_stats["rank"])


# --- off the exact case: the explicit diagonal and direction ------------------------------
@pytest.fixture(scope="module")
def mlp():
    return _mlp_problem()


def test_diagonal_equals_the_explicit_gauss_newton_diagonal_in_the_kept_basis(mlp):
    """Λ = diag(Uᵀ (JᵀJ) U) per layer, U = kron(U_G, U_A) the eigenvectors of KHIG's factors,
    J the layer's Jacobian from jacfwd; and it is not KHIG's γα/b here (the correction matters)."""
    params, batch, objective = mlp
    found = _compiled(layer_corrections, objective, params, batch)
    factors = _compiled(layer_factors, objective, params, batch)
    assert [int(leaf) for leaf, *_ in found] == [0, 2]  # leaves: l1.W, l1.b, l2.W, l2.b
    for name, (_, q_g, q_a, lam), f in zip(("l1", "l2"), found, factors):
        q_g, q_a, lam = np.asarray(q_g), np.asarray(q_a), np.asarray(lam)
        for q, m in ((q_g, np.asarray(f.G)), (q_a, np.asarray(f.A))):  # the factors' eigenbases
            rotated = q.T @ m @ q
            np.testing.assert_allclose(rotated - np.diag(np.diag(rotated)), 0.0, atol=1e-10 * np.abs(m).max())
        J = _layer_jacobian(objective, params, batch, name)
        U = np.kron(q_g, q_a)
        explicit = np.diag(U.T @ (J.T @ J) @ U).reshape(lam.shape)
        np.testing.assert_allclose(lam, explicit, rtol=1e-9, atol=1e-12 * explicit.max())
        products = np.outer(np.diag(q_g.T @ np.asarray(f.G) @ q_g), np.diag(q_a.T @ np.asarray(f.A) @ q_a)) / BATCH
        assert np.max(np.abs(products - explicit)) > 1e-2 * explicit.max()


def _second_batch(batch):
    keys = jax.random.split(jax.random.key(11), 2)
    return {"x": jax.random.normal(keys[0], batch["x"].shape), "t": jax.random.normal(keys[1], batch["t"].shape)}


@pytest.mark.parametrize("basis_every", [1, 2])
def test_direction_in_the_kept_basis_and_its_refresh(mlp, basis_every):
    """Second step: U from this batch's factors (k = 1) or the first step's (k = 2, kept),
    ΔW̄ = U φ(diag(Uᵀ JᵀJ U)) Uᵀ vec ∇W̄, φ(λ) = (λ + δλ_max)^p above τ²λ_max; J from jacfwd."""
    params, batch, objective = mlp
    lr, tau, damping = 0.05, 1e-3, 1e-3
    method = _method(KroneckerPower(-0.75, tau, damping), lr, basis_every)
    second = _second_batch(batch)
    p1, state, _ = _step(method, objective, params, method.init(params), batch)
    p2, state, stats = _step(method, objective, p1, state, second)
    assert int(stats["refreshed"]) == (basis_every == 1)
    basis_from = (p1, second) if basis_every == 1 else (params, batch)
    bases = _compiled(layer_corrections, objective, *basis_from)
    grad = jax.jit(jax.grad(lambda p: objective.batch_loss(p, second)))(p1)
    for name, (_, q_g, q_a, _) in zip(("l1", "l2"), bases):
        U = np.kron(np.asarray(q_g), np.asarray(q_a))
        J = _layer_jacobian(objective, p1, second, name)
        lam = np.diag(U.T @ (J.T @ J) @ U)
        keep = lam > tau**2 * lam.max()
        phi = np.where(keep, (np.where(keep, lam, 1.0) + damping * lam.max()) ** -0.75, 0.0)
        want = (U @ (phi * (U.T @ _full(grad, name).ravel()))).reshape(_full(grad, name).shape)
        got = (_full(p1, name) - _full(p2, name)) / lr
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())


def test_settings_are_checked_in_one_line():
    with pytest.raises(ValueError, match=r"^basis_every must be >= 1, got 0$"):
        _method(KroneckerPower(), basis_every=0)
    params, batch, objective = _linear_problem(False)
    rule = KroneckerPower()
    # the projected signals and inputs and the kept bases come on top of KHIG's signals and factors
    extra = (7 * 3 * 4 + 7 * 6 + 4**2 + 6**2) * 8  # rows·d_out + b·d_in' projections, d_out² + d_in'² bases
    assert _method(rule).footprint(objective, params, batch) == rule.footprint(objective, params, batch) + extra
    control = KeptEigenbasis()
    with pytest.raises(ValueError, match=r"^a kept Kronecker eigenbasis needs a KroneckerPower rule, got Gradient$"):
        control.direct(physgrad.methods.Gradient(), objective, params, batch, control.init(params), None)


@pytest.mark.costly("the one end-to-end run of ekhig: registry, command line and training together")
def test_ekhig_is_registered_with_hig_defaults_and_trains_oscillators_from_the_cli(tmp_path):
    assert "ekhig" in METHODS and describe("ekhig").startswith("Eigenvalue-corrected KHIG")
    assert paper_defaults(PROBLEMS["oscillators"], "ekhig") == paper_defaults(PROBLEMS["oscillators"], "hig")
    method = METHODS["ekhig"](basis_every=3)
    assert isinstance(method, EigenCorrectedKronecker) and method.basis_every == 3
    settings = {"n_train": "64", "n_test": "64", "batch_size": "16", "eval_every": "8"}
    test = cli_test_losses(tmp_path / "run", "oscillators", "ekhig", 16, settings)
    assert len(test) == 3 and all(np.isfinite(test))
    assert test[0] > test[1] > test[2], test

"""The structured half-inverse route against independent references.

References: the explicit Jacobian from ``jax.jacrev`` turned into NumPy float64 (its Gram
matrix, and the truncated ``V Σ^κ Uᵀ g`` from ``numpy.linalg.svd``), and the ``gram``
route that forms J. Networks: MLPs with tanh/ReLU, with and without biases, a layer
written as ``x @ W``, a mixed convolution + dense network (explicit rows for the
convolution, several leaf groups), complex outputs, and 4 forced devices.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad import routes
from physgrad.distributed import make_mesh, replicated, shard_batch, use_mesh
from physgrad.jacobian import stacked_jacobian
from physgrad.methods.base import Objective
from physgrad.nets import MLP
from physgrad.routes import JointJacobian, find_structure
from physgrad.routes.structured import cross_gram, factors


class NoBiasMLP(eqx.Module):
    """Dense layers without biases (``eqx.nn.Linear(use_bias=False)``): every parameter is
    a dense weight, so no explicit rows at all."""

    layers: tuple

    def __init__(self, sizes, key):
        keys = jax.random.split(key, len(sizes) - 1)
        self.layers = tuple(eqx.nn.Linear(a, b, use_bias=False, key=k) for a, b, k in zip(sizes[:-1], sizes[1:], keys))

    def __call__(self, x):
        for layer in self.layers[:-1]:
            x = jax.nn.relu(layer(x))
        return self.layers[-1](x)


class RightMultiply(eqx.Module):
    """A hand-written dense layer ``x @ W`` (W stored d_in × d_out), then a layer whose
    weight is used twice (not a single dense application: explicit rows)."""

    w: jax.Array
    shared: jax.Array

    def __init__(self, key):
        k1, k2 = jax.random.split(key)
        self.w = jax.random.normal(k1, (3, 5)) / 2
        self.shared = jax.random.normal(k2, (5, 5)) / 3

    def __call__(self, x):
        h = jnp.tanh(x @ self.w)
        return self.shared @ jnp.tanh(self.shared @ h)


class ConvDense(eqx.Module):
    """A mixed network: 1D convolution (explicit rows) → flatten → dense layers."""

    conv: eqx.nn.Conv1d
    mlp: MLP

    def __init__(self, key):
        k1, k2 = jax.random.split(key)
        self.conv = eqx.nn.Conv1d(1, 2, 3, padding="SAME", key=k1)
        self.mlp = MLP((16, 12, 3), jax.nn.tanh, key=k2)

    def __call__(self, x):
        return self.mlp(jnp.tanh(self.conv(x[None])).ravel())


def _objective(net, physics=jnp.sin, loss=None):
    params, static = eqx.partition(net, eqx.is_inexact_array)
    predict = lambda p, s: physics(eqx.combine(p, static)(s["x"]))  # noqa: E731
    loss = loss or (lambda y, s: jnp.sum((y - s["t"]) ** 2))
    return Objective(predict, loss), params


def _batch(n_in, n_out, b=6, key=1, complex_target=False):
    x = jax.random.normal(jax.random.key(key), (b, n_in))
    t = jax.random.normal(jax.random.key(key + 1), (b, n_out))
    return {"x": x, "t": t * (1 + 1j) if complex_target else t}


def _explicit(objective, params, batch):
    """The explicit J and g in NumPy float64 (jitted: one program each, where eager calls
    compile op by op)."""
    jac, y = jax.jit(lambda p, b: stacked_jacobian(objective.predict, p, b))(params, batch)
    _, g = jax.jit(lambda p, b, y: JointJacobian.of(objective, p, b).loss_and_gradient(y))(params, batch, y)
    return np.asarray(jac, np.float64), np.asarray(g, np.float64)


def _svd_formula(j, g, exponent, truncation):
    """``V Σ^κ Uᵀ g`` with σ ≤ τ σ_max dropped, and the singular values, in NumPy float64."""
    u, s, vt = np.linalg.svd(j, full_matrices=False)
    keep = s > truncation * s.max()
    return vt[keep].T @ (s[keep] ** exponent * (u[:, keep].T @ g)), s


def _numpy_reference(objective, params, batch, exponent, truncation):
    """``V Σ^κ Uᵀ g`` with σ ≤ τ σ_max dropped, from the explicit J in NumPy float64."""
    return _svd_formula(*_explicit(objective, params, batch), exponent, truncation)


def _direction(route, objective, params, batch, exponent, truncation):
    """The route's direction, jitted as the engine runs it (one program, where an eager call
    compiles op by op)."""
    return jax.jit(lambda p, b: route(objective, p, b, exponent, truncation)[0])(params, batch)


def _between(s, k):
    """A truncation τ with σ_k > τ σ_max > σ_{k+1}, well away from both."""
    return float(np.sqrt(s[k] * s[k + 1]) / s[0])


NETWORKS = {
    "mlp_tanh": lambda: MLP((3, 8, 6, 2), jax.nn.tanh, key=jax.random.key(0)),
    "mlp_relu": lambda: MLP((3, 10, 7, 2), jax.nn.relu, key=jax.random.key(2)),
    "no_bias": lambda: NoBiasMLP((3, 9, 2), jax.random.key(3)),
    "x_at_w": lambda: RightMultiply(jax.random.key(4)),
}
OUTPUTS = {"mlp_tanh": 2, "mlp_relu": 2, "no_bias": 2, "x_at_w": 5}


@pytest.mark.parametrize("name", sorted(NETWORKS))
def test_structured_gram_equals_the_explicit_gram(name):
    net = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, NETWORKS[name]())
    objective, params = _objective(net)
    batch = _batch(3, OUTPUTS[name])
    rows = 6 * OUTPUTS[name]
    plan = find_structure(objective.predict, params, jax.tree.map(lambda a: a[0], batch), rows)
    gram = jax.jit(lambda p, b: (lambda block: cross_gram(plan, block, block))(factors(plan, p, b)[0]))
    jac, _ = jax.jit(lambda p, b: stacked_jacobian(objective.predict, p, b))(params, batch)
    j = np.asarray(jac)
    np.testing.assert_allclose(np.asarray(gram(params, batch)), j @ j.T, rtol=1e-12, atol=1e-12 * np.abs(j @ j.T).max())


def test_dense_layers_are_found_in_the_program_and_the_rest_is_explicit():
    sample = {"x": jnp.zeros(3, jnp.float32), "t": jnp.zeros(2, jnp.float32)}
    objective, params = _objective(MLP((3, 8, 6, 2), jax.nn.tanh, key=jax.random.key(0)))
    plan = find_structure(objective.predict, params, sample, rows=12)
    assert [(u.d_in, u.d_out, u.transposed) for u in plan.dense] == [(3, 8, False), (8, 6, False), (6, 2, False)]
    assert all(u.bias is not None for u in plan.dense) and plan.explicit_parameters == 0  # biases folded in
    objective, params = _objective(RightMultiply(jax.random.key(4)))
    plan = find_structure(objective.predict, params, {"x": jnp.zeros(3), "t": jnp.zeros(5)}, rows=12)
    assert [(u.d_in, u.d_out, u.transposed) for u in plan.dense] == [(3, 5, True)]
    assert plan.explicit_parameters == 25  # the weight used twice
    # a network applied point-wise inside predict (vmap): one weight, several inputs each
    net = MLP((1, 4, 1), jax.nn.tanh, key=jax.random.key(5))
    params, static = eqx.partition(net, eqx.is_inexact_array)
    pointwise = lambda p, s: jax.vmap(eqx.combine(p, static))(s["x"][:, None]).ravel()  # noqa: E731
    plan = find_structure(pointwise, params, {"x": jnp.zeros(3)}, rows=3)
    assert plan.dense == () and plan.explicit_parameters == 4 + 4 + 4 + 1

    # a bias used elsewhere too is not folded: its rows stay explicit
    class TwiceBias(eqx.Module):
        w: jax.Array
        b: jax.Array

        def __call__(self, x):
            return jnp.tanh(self.w @ x + self.b) * self.b

    params = TwiceBias(jnp.ones((2, 3)), jnp.ones(2))
    plan = find_structure(lambda p, s: p(s["x"]), params, {"x": jnp.zeros(3)}, rows=2)
    assert plan.dense[0].bias is None and plan.explicit_parameters == 2


@pytest.mark.parametrize("name", sorted(NETWORKS))
@pytest.mark.parametrize("exponent", [-0.5, -1.0])
def test_structured_update_equals_the_numpy_svd_formula_with_dropped_singular_values(name, exponent):
    net = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, NETWORKS[name]())
    objective, params = _objective(net)
    batch = _batch(3, OUTPUTS[name])
    j, g = _explicit(objective, params, batch)  # once, for the spectrum and the direction
    _, s = _svd_formula(j, g, exponent, 0.0)
    tau = _between(s, len(s) // 2)  # drops the smaller half of the spectrum
    want, _ = _svd_formula(j, g, exponent, tau)
    got, loss, _ = jax.jit(lambda p, b: routes.Structured()(objective, p, b, exponent, tau))(params, batch)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-8, atol=1e-10 * np.abs(want).max())
    assert float(loss) == pytest.approx(float(objective.batch_loss(params, batch)), rel=1e-12)


@pytest.mark.parametrize("name", ["mlp_tanh", "mlp_relu", "no_bias"])
def test_structured_update_equals_the_gram_route_in_float32(name):
    net = jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, NETWORKS[name]())
    objective, params = _objective(net)
    batch = jax.tree.map(lambda a: a.astype(jnp.float32), _batch(3, 2))
    want = _direction(routes.Gram(), objective, params, batch, -0.5, 1e-3)
    got = _direction(routes.Structured(), objective, params, batch, -0.5, 1e-3)
    assert got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=2e-4, atol=2e-5 * float(jnp.abs(want).max()))


def _mixed():
    net = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, ConvDense(jax.random.key(6)))
    return _objective(net) + (_batch(8, 3, b=5),)


# one explicit group; several (the VJP path, in the slow tier)
@pytest.mark.parametrize("chunk", [2**26, pytest.param(4, marks=pytest.mark.slow)])
def test_mixed_conv_dense_network_equals_the_gram_route(chunk):
    objective, params, batch = _mixed()
    rows = 5 * 3
    plan = find_structure(
        objective.predict, params, jax.tree.map(lambda a: a[0], batch), rows, chunk_elements=chunk * rows
    )
    assert len(plan.dense) == 2 and plan.explicit_parameters == 2 * 3 + 2  # the convolution's kernel and bias
    assert (len(plan.groups) > 1) == (chunk == 4)
    for exponent in (-0.5, -1.0):
        want = _direction(routes.Gram(), objective, params, batch, exponent, 1e-6)
        got = _direction(routes.Structured(chunk_elements=chunk * rows), objective, params, batch, exponent, 1e-6)
        np.testing.assert_allclose(
            np.asarray(got), np.asarray(want), rtol=1e-8, atol=1e-10 * float(jnp.abs(want).max())
        )


def test_complex_outputs_equal_the_gram_route():
    """A real network, complex physics (as the quantum dipole): J has (Re, Im) rows."""
    net = jax.tree.map(
        lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a,
        MLP((3, 8, 2), jax.nn.tanh, key=jax.random.key(7)),
    )
    objective, params = _objective(
        net, physics=lambda u: jnp.exp(1j * u) * (1 + u), loss=lambda y, s: jnp.sum(jnp.abs(y - s["t"]) ** 2)
    )
    batch = _batch(3, 2, complex_target=True)
    j, g = _explicit(objective, params, batch)  # once, for both exponents
    for exponent in (-0.5, -1.0):
        want, _ = _svd_formula(j, g, exponent, 1e-6)
        got = _direction(routes.Structured(), objective, params, batch, exponent, 1e-6)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-8, atol=1e-10 * np.abs(want).max())


def test_tall_jacobian_goes_to_the_gram_route():
    objective, params = _objective(MLP((3, 2, 2), jax.nn.tanh, key=jax.random.key(8), dtype=jnp.float64))
    batch = _batch(3, 2, b=20)  # 40 rows, 14 parameters
    want, _ = _numpy_reference(objective, params, batch, -0.5, 1e-6)
    got = _direction(routes.Structured(), objective, params, batch, -0.5, 1e-6)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-8, atol=1e-10 * np.abs(want).max())


def test_auto_picks_structured_for_dense_networks_and_gram_otherwise():
    objective, params = _objective(MLP((3, 8, 6, 2), jax.nn.tanh, key=jax.random.key(0)))
    assert isinstance(routes.Auto().choose(objective, params, _batch(3, 2)), routes.Structured)
    conv = eqx.nn.Conv1d(1, 1, 3, padding="SAME", key=jax.random.key(1))
    objective, params = _objective(conv, physics=lambda y: jnp.sin(y[0]))
    assert isinstance(
        routes.Auto().choose(objective, params, {"x": jnp.ones((2, 1, 8)), "t": jnp.ones((2, 8))}), routes.Gram
    )


def test_structured_footprint_is_far_below_the_gram_routes():
    objective, params = _objective(MLP((64, 256, 256, 64), jax.nn.tanh, key=jax.random.key(0)))
    batch = _batch(64, 64, b=16)
    rows, size = 16 * 64, sum(x.size for x in jax.tree.leaves(params))
    gram = routes.Gram().footprint(objective, params, batch)
    assert gram == rows * size * (4 + 8) + 3 * rows**2 * 8
    assert routes.Structured().footprint(objective, params, batch) < gram / 4


@pytest.mark.skipif(jax.device_count() < 4, reason="needs 4 (forced host) devices")
@pytest.mark.parametrize("case", ["mixed", pytest.param("complex", marks=pytest.mark.slow)])
def test_structured_route_sharded_over_4_devices_equals_one_device(case):
    if case == "mixed":
        objective, params, batch = _mixed()
        batch = jax.tree.map(lambda a: jnp.concatenate([a, a[:3] * 0.5]), batch)  # 8 samples
    else:
        net = jax.tree.map(lambda a: a.astype(jnp.float64), MLP((3, 8, 2), jax.nn.tanh, key=jax.random.key(7)))
        objective, params = _objective(
            net, physics=lambda u: jnp.exp(1j * u) * (1 + u), loss=lambda y, s: jnp.sum(jnp.abs(y - s["t"]) ** 2)
        )
        batch = _batch(3, 2, b=8, complex_target=True)
    want = _direction(routes.Structured(), objective, params, batch, -0.5, 1e-6)
    mesh = make_mesh(4)
    with use_mesh(mesh):
        step = jax.jit(lambda p, b: routes.Structured()(objective, replicated(p), shard_batch(b), -0.5, 1e-6)[0])
        got = step(params, batch)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-9, atol=1e-11 * float(jnp.abs(want).max()))

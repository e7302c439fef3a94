"""K-FAC through the simulator (kfac-jax): the exact-curvature step against a NumPy
Gauss–Newton formula, training through the engine, and the one-line refusals."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.engine import Phase, build_setup, make_evaluate, make_step
from physgrad.harness.registry import PROBLEMS
from physgrad.methods import Objective
from physgrad.methods.kfac import kfac
from physgrad.nets import Dense

N_IN, N_OUT, M = 3, 4, 5  # x ∈ ℝ³, network output ∈ ℝ⁴, simulator output y = A(Wx + b) ∈ ℝ⁵


def linear_case(batch_size):
    rng = np.random.default_rng(0)
    a = rng.standard_normal((M, N_OUT))
    layer = Dense(N_IN, N_OUT, key=jax.random.key(0), dtype=jnp.float64)
    layer = eqx.tree_at(lambda l: l.bias, layer, jnp.asarray(rng.standard_normal(N_OUT)))
    batch = {
        "x": jnp.asarray(rng.standard_normal((batch_size, N_IN))),
        "t": jnp.asarray(rng.standard_normal((batch_size, M))),
    }
    objective = Objective(
        predict=lambda p, s: jnp.asarray(a) @ p(s["x"]),
        loss=lambda y, s: 0.5 * jnp.sum((y - s["t"]) ** 2),
    )
    return a, layer, batch, objective


def numpy_gauss_newton_step(a, w, b, x, t, damping):
    """θ − (JᵀJ/n + λI)⁻¹ Jᵀr/n for the batch-mean loss (1/n) Σ ½‖A(Wxᵢ + b) − tᵢ‖², with
    θ = (vec W row-major, b) and Jᵢ = [A ⊗ xᵢᵀ, A]; float64."""
    n = x.shape[0]
    jac = np.concatenate([np.concatenate([np.kron(a, xi[None, :]), a], axis=1) for xi in x])  # (n·m, |θ|)
    r = np.concatenate([a @ (w @ xi + b) - ti for xi, ti in zip(x, t)])
    theta = np.concatenate([w.ravel(), b])
    step = np.linalg.solve(jac.T @ jac / n + damping * np.eye(theta.size), jac.T @ r / n)
    return theta - step


@pytest.mark.parametrize(
    "blocks,batch_size",
    [("full", 8), ("kfac", 1)],  # a full block is exact for any batch; Kronecker factors for one sample
)
def test_exact_curvature_step_is_the_gauss_newton_step(blocks, batch_size):
    a, layer, batch, objective = linear_case(batch_size)
    damping = 0.1
    method = kfac(adaptive=False, lr=1.0, momentum=0.0, damping=damping, adaptive_damping=False, blocks=blocks,
                  estimation="ggn_exact", inverse_every=1, exact_inverses=True)  # fmt: skip
    params, static = eqx.partition(layer, eqx.is_inexact_array)
    state = method.init(params)
    new, state, stats = jax.jit(lambda p, s, b: method.step(objective, p, s, b))(params, state, batch)
    want = numpy_gauss_newton_step(a, np.asarray(layer.weight), np.asarray(layer.bias), np.asarray(batch["x"]),
                                   np.asarray(batch["t"]), damping)  # fmt: skip
    got = np.concatenate([np.asarray(new.weight).ravel(), np.asarray(new.bias)])
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)
    assert new.weight.dtype == jnp.float64
    assert float(stats["loss"]) == pytest.approx(float(objective.batch_loss(params, batch)), rel=1e-12)


# Small settings: each test compiles one step (kfac-jax traces the network several times).
TRAINING = {
    "hig_toy": ({"n_train": 64, "n_test": 16}, 16, 40),
    "exp_inverse": ({"n_train": 64, "n_test": 16}, 16, 40),
}


@pytest.mark.parametrize(
    "name", [n if n == "hig_toy" else pytest.param(n, marks=pytest.mark.slow) for n in sorted(TRAINING)]
)
def test_kfac_trains_an_open_loop_problem_through_the_engine(name):
    settings, batch_size, steps = TRAINING[name]
    # damping_interval=1: one traced variant of kfac-jax's step (halves compilation here).
    setup = build_setup(PROBLEMS[name](**settings), [Phase(kfac(damping_interval=1), batch_size=batch_size)], seed=0)
    step, evaluate = make_step(setup, batch_size), make_evaluate(setup)
    data = setup.data["train"]
    order = jnp.arange(settings["n_train"], dtype=jnp.int32)
    params, state = setup.params, setup.method.init(setup.params)
    before = float(evaluate(params, data)["loss"])
    for i in range(steps):
        params, state, stats = step(params, state, data, order, jnp.int32(i % (settings["n_train"] // batch_size)))
        assert np.isfinite(float(stats["loss"]))
    after = float(evaluate(params, data)["loss"])
    assert after < 0.7 * before, (before, after)
    assert step._cache_size() == 1  # the state keeps its structure and dtypes from init on
    assert jax.tree.map(lambda a: a.dtype, params) == jax.tree.map(lambda a: a.dtype, setup.params)


def test_complex_simulator_output_is_refused_in_one_line():
    problem = PROBLEMS["quantum_dipole"](n_train=8, n_test=8)
    setup = build_setup(problem, [Phase(kfac(), batch_size=4)], seed=0)
    batch = jax.tree.map(lambda a: a[:4], setup.data["train"])
    with pytest.raises(ValueError, match=r"^kfac: the simulator output is complex .* use gn, hig or adam$") as info:
        setup.method.step(setup.objective, setup.params, setup.method.init(setup.params), batch)
    assert "\n" not in str(info.value)
    # under the engine's jit the same line comes first (JAX appends its traceback note)
    with pytest.raises(ValueError) as info:
        make_step(setup, 4)(setup.params, setup.method.init(setup.params), setup.data["train"], jnp.arange(8), 0)
    assert (
        str(info.value).splitlines()[0]
        == "kfac: the simulator output is complex (complex64) and kfac-jax's losses are real; use gn, hig or adam"
    )


def test_a_closed_loop_rollout_is_not_applicable_from_shapes():
    """cartpole's predict returns its trajectory (a tuple) from a controller applied every
    time step: the bench lists kfac as not applicable there, with the reason, instead of a
    crash inside kfac-jax's tracer when the step is built."""
    from physgrad.harness.bench.applicability import applicability

    verdicts = {v.method: v for v in applicability("cartpole", ["kfac", "adam"])}
    assert verdicts["adam"].status == "applicable" and verdicts["kfac"].status == "not applicable"
    assert (
        verdicts["kfac"].reason.startswith("kfac: predict returns a tuple of") and "\n" not in verdicts["kfac"].reason
    )


@pytest.mark.slow  # ~8 s: the dipole's abstract setup, twice
def test_complex_simulator_output_is_refused_from_shapes_by_the_bench_and_the_preflight():
    """Before any data exist: the bench lists kfac as not applicable on the dipole (not as
    three failed runs), and a run's memory preflight refuses it in the same line."""
    from physgrad.engine.setup import preflight
    from physgrad.errors import ConfigError
    from physgrad.harness.bench.applicability import applicability

    verdicts = {v.method: v for v in applicability("quantum_dipole", ["kfac", "adam"])}
    assert verdicts["adam"].status == "applicable"
    assert verdicts["kfac"].status == "not applicable"
    assert verdicts["kfac"].reason.startswith("kfac: the simulator output is complex (complex64)")
    with pytest.raises(ConfigError, match=r"kfac: the simulator output is complex"):
        preflight(PROBLEMS["quantum_dipole"](n_train=8, n_test=8), [Phase(kfac(), batch_size=4)], seed=0)


def test_settings_are_checked_and_the_factory_is_command_line_ready():
    import inspect

    signature = inspect.signature(kfac)
    assert all(p.kind is p.KEYWORD_ONLY and isinstance(p.default, bool | int | float | str)
               for p in signature.parameters.values())  # fmt: skip
    assert kfac.__doc__.startswith("K-FAC (Martens & Grosse 2015) through the simulator with kfac-jax:")
    with pytest.raises(ValueError, match="unknown blocks 'diag'; valid choices: kfac, full"):
        kfac(blocks="diag")
    with pytest.raises(ValueError, match="unknown loss_hessian"):
        kfac(loss_hessian="fisher")
    with pytest.raises(ValueError, match="not differentiable"):
        kfac().check(Objective(predict=lambda p, s: p, loss=lambda y, s: y, differentiable=False))


# --- kfac-jax's precon_power = −¾ is KHIG's direction (issue 51: what kfac-jax already had) -----
def _mlp_through_nonlinear_physics():
    """A 2-layer tanh MLP of physgrad Dense layers through a nonlinear, sample-dependent
    simulator; the loss ½‖y − t‖² has the Hessian I, so kfac-jax's Gauss–Newton is (1/b) JᵀJ."""
    keys = jax.random.split(jax.random.key(7), 6)
    params = (Dense(3, 5, key=keys[0], dtype=jnp.float64), Dense(5, 4, key=keys[1], dtype=jnp.float64))
    P = jax.random.normal(keys[2], (6, 4)) / 2

    def predict(p, s):
        z = P @ p[1](jnp.tanh(p[0](s["x"])))
        return jnp.sin(z) * (1.0 + s["x"][0] ** 2) + 0.1 * z**3

    def batch(key):
        kx, kt = jax.random.split(key)
        return {"x": jax.random.normal(kx, (9, 3)), "t": jax.random.normal(kt, (9, 6))}

    return params, batch(keys[3]), batch(keys[4]), Objective(predict, lambda y, s: 0.5 * jnp.sum((y - s["t"]) ** 2))


@pytest.mark.costly("the credit test of issue 51: kfac-jax's optimizer traced end to end, once")
def test_kfac_jax_at_precon_power_three_quarters_is_khig_without_truncation_or_damping():
    """kfac-jax driven end to end (its Optimizer inside physgrad's kfac) with precon_power −¾,
    exact inverses of ggn_exact Kronecker blocks, fresh factors (curvature_ema 0, inverse
    every step), lr 1, no momentum and a fixed damping of 1e-12 (kfac needs one > 0): the
    step is KHIG's direction with truncation and damping 0 on both of two batches, times
    b^{3/4}: kfac-jax's factors are batch means (the curvature of the mean loss, (1/b²) G ⊗ A)
    where KHIG's are sums ((1/b) G ⊗ A, the curvature JᵀJ of HIG), a scalar on the step."""
    import physgrad

    params, first, second, objective = _mlp_through_nonlinear_physics()
    method = kfac(adaptive=False, lr=1.0, momentum=0.0, damping=1e-12, adaptive_damping=False, curvature_ema=0.0,
                  inverse_every=1, estimation="ggn_exact", exact_inverses=True, precon_power=-0.75)  # fmt: skip
    step = eqx.filter_jit(lambda p, s, b: method.step(objective, p, s, b))
    khig = eqx.filter_jit(physgrad.kronecker_hig(objective.predict, objective.loss, truncation=0.0, damping=0.0))
    state = method.init(params)
    for batch in (first, second):
        new, state, _ = step(params, state, batch)
        want, _ = khig(params, batch)
        for got, w in zip(jax.tree.leaves(jax.tree.map(lambda a, b: a - b, params, new)), jax.tree.leaves(want)):
            np.testing.assert_allclose(np.asarray(got), 9**0.75 * np.asarray(w), rtol=1e-8, atol=1e-10)
        params = new


def test_precon_power_is_checked_and_registered_as_kfac_hig():
    from physgrad.harness.registry import METHODS, describe, paper_defaults

    with pytest.raises(
        ValueError, match=r"^kfac needs precon_power < 0, and exact_inverses=true unless -1; got -0.75$"
    ):
        kfac(precon_power=-0.75)
    with pytest.raises(ValueError, match=r"^kfac needs precon_power < 0, .* got 0.5$"):
        kfac(precon_power=0.5, exact_inverses=True)
    method = METHODS["kfac_hig"]()
    assert (method.precon_power, method.exact_inverses, method.estimation) == (-0.75, True, "ggn_exact")  # pyright: ignore[reportAttributeAccessIssue]
    assert describe("kfac_hig").startswith("K-FAC (kfac-jax) at HIG's power")
    assert paper_defaults(PROBLEMS["oscillators"], "kfac_hig") == paper_defaults(PROBLEMS["oscillators"], "kfac")

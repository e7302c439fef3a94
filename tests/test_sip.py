"""The SIP method: exact targets on linear physics, no gradient through the simulator,
failure handling, and direct optimisation (the 2D toy) against hand-written loops."""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from physgrad import Budget
from physgrad.engine import Placement, Steps, TrainSettings
from physgrad.errors import ConfigError
from physgrad.harness.config import make_config
from physgrad.harness.registry import METHODS, PROBLEMS
from physgrad.harness.train import build, make_step, train
from physgrad.methods import L1Proxy
from physgrad.problems import ExpInverse

SMALL = {"exp_inverse": {"n_train": 256, "n_test": 16}, "sine": {"n_train": 256, "n_test": 16}}


def one_step(problem, method, settings=None, seed=0):
    settings = {**SMALL.get(problem, {}), **(settings or {})}
    config = make_config(problem, method, budget=Budget(steps=1), seed=seed, settings=settings)
    setup = build(config)
    stage = setup.stages[0]
    batch = jax.tree.map(lambda a: a[: stage.batch_size], setup.data["train"])
    return setup, stage, batch


def jit_step(method, objective, params, batch):
    return jax.jit(lambda p, b: method.step(objective, p, method.init(p), b))(params, batch)


def local_inverse(rule, objective, x, y, batch):
    """``rule.local_inverse`` compiled as one program (eagerly, an iterative solver compiles
    each of its operations on its own: 15 s instead of 1 s for sine's Newton solve)."""
    return eqx.filter_jit(rule.local_inverse)(objective, x, y, batch)


def test_sip_on_linear_invertible_physics_targets_the_ground_truth():
    setup, stage, batch = one_step(
        "poisson", "sip", {"resolution": 16, "n_train": 8, "n_test": 8, "batch_size": 8, "levels": 2}
    )
    obj = setup.objective
    x = eqx.filter_jit(jax.vmap(obj.network_output, (None, 0)))(setup.params, batch)
    y = eqx.filter_jit(jax.vmap(obj.simulate))(x, batch)
    x_tilde, ok = local_inverse(stage.method.rule, obj, x, y, batch)
    assert bool(jnp.all(ok))
    np.testing.assert_allclose(x_tilde, batch["x_gt"], atol=2e-4)  # float32 U-Net output, exact inverse


def test_sip_gradient_is_the_supervised_gradient_on_linear_physics():
    """η = 1, exact inverse: ∇_θ proxy = ∇_θ (1/b) Σ ½‖f(y*) − x*‖² (SIP = supervised)."""
    settings = {
        "resolution": 16,
        "n_train": 8,
        "n_test": 8,
        "batch_size": 8,
        "levels": 2,
        "lr": 1.0,
        "optimizer": "sgd",
    }
    setup, stage, batch = one_step("poisson", "sip", settings)
    obj = setup.objective

    def supervised(p):
        x = jax.vmap(obj.network_output, (None, 0))(p, batch)
        return 0.5 * jnp.sum((x - batch["x_gt"]) ** 2) / x.shape[0]

    # the reference gradient compiled as one program (eagerly, each U-Net operation and its
    # transpose compiles on its own)
    expected = jax.tree.map(lambda p, g: p - g, setup.params, jax.jit(jax.grad(supervised))(setup.params))
    new, _, stats = jit_step(stage.method, obj, setup.params, batch)
    for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-6)
    assert int(stats["inverse_failures"]) == 0


@pytest.mark.parametrize("solver", ["gauss_newton", "linear_solve", "lbfgs"])
def test_generic_solvers_agree_with_the_analytic_inverse(solver):
    """exp is invertible per sample: GN (one step), Krylov (one Newton–Krylov step) and
    L-BFGS are different routes; at η small enough for GN to be accurate they match log."""
    setup, stage, batch = one_step(
        "exp_inverse", "sip", {"solver": solver, "eta": 1e-3, "tol": 1e-12, "max_steps": 200}
    )
    obj = setup.objective
    x = eqx.filter_jit(jax.vmap(obj.network_output, (None, 0)))(setup.params, batch).astype(jnp.float64)
    y = jnp.exp(x)
    x_tilde, ok = local_inverse(stage.method.rule, obj, x, y, batch)
    expected = np.log(np.asarray(y) + 1e-3 * (np.asarray(batch["y"], np.float64) - np.asarray(y)))
    assert bool(jnp.all(ok))
    np.testing.assert_allclose(x_tilde, expected, atol=1e-5)


@jax.custom_jvp
def untouchable_exp(x):
    return jnp.exp(x)


@untouchable_exp.defjvp
def _untouchable(primals, tangents):
    raise RuntimeError("the simulator was differentiated")


class NonDifferentiableExp(ExpInverse):
    name: ClassVar[str] = "nondiff_exp"

    def simulate(self, x, sample):
        return untouchable_exp(x)


def test_the_proxy_sends_no_gradient_into_the_simulator(tmp_path, monkeypatch):
    monkeypatch.setitem(PROBLEMS, "nondiff_exp", NonDifferentiableExp)
    budget = Budget(steps=20)
    summary = train(make_config("nondiff_exp", "sip", budget=budget), tmp_path / "sip")
    assert summary["status"] == "finished" and summary["steps"] == 20
    with pytest.raises(RuntimeError, match="differentiated"):  # DP must differentiate it
        train(make_config("nondiff_exp", "adam", budget=budget), tmp_path / "adam")


def test_failed_solves_are_counted_and_contribute_nothing():
    setup, stage, batch = one_step("exp_inverse", "sip", {"eta": 1.0})
    obj = setup.objective
    # The analytic inverse log(y_t) is NaN where y_t < 0: force that with a huge η.
    bad = METHODS["sip"](eta=1e6, solver="analytic")
    x = eqx.filter_jit(jax.vmap(obj.network_output, (None, 0)))(setup.params, batch)
    y = jnp.exp(x)
    x_tilde, ok = local_inverse(bad.rule, obj, x, y, batch)
    failed = ~np.asarray(ok)
    assert failed.any()
    np.testing.assert_array_equal(np.asarray(x_tilde)[failed], np.asarray(x)[failed])
    _, _, stats = jit_step(bad, obj, setup.params, batch)
    assert int(stats["inverse_failures"]) == failed.sum() and np.isfinite(float(stats["proxy"]))


def test_inverse_failures_reach_the_metrics_and_the_summary(tmp_path):
    settings = {**SMALL["exp_inverse"], "eta": 1e6, "eval_every": 2}  # every log(y_t < 0) fails
    summary = train(make_config("exp_inverse", "sip", budget=Budget(steps=4), settings=settings), tmp_path)
    assert summary["step_stat_totals"]["inverse_failures"] > 0
    text = (tmp_path / "metrics.csv").read_text()
    assert "train,step_inverse_failures" in text and "train,step_proxy" in text


def test_the_y_step_is_exact_at_eta_one_in_float32():
    """y_t = (1 − η) y + η y* gives y* bit-exactly at η = 1, even for y* = e⁻¹² ≪ y = 148."""
    setup, stage, batch = one_step("exp_inverse", "sip", {"precision": "float32"})
    obj = setup.objective
    small = {"x_gt": jnp.full((2, 1), -12.0, jnp.float32), "y": jnp.full((2, 1), np.exp(-12.0), jnp.float32)}
    x = jnp.full((2, 1), 5.0, jnp.float32)
    x_tilde, ok = local_inverse(stage.method.rule, obj, x, jnp.exp(x), small)
    assert bool(jnp.all(ok))
    np.testing.assert_allclose(x_tilde, -12.0, atol=1e-5)


def test_l1_proxy_gradient_is_the_sign():
    setup, stage, batch = one_step("sine", "sip", {"optimizer": "sgd", "lr": 1.0, "batch_size": 4})
    obj, method = setup.objective, stage.method
    assert isinstance(method.rule.proxy, L1Proxy)
    x = eqx.filter_jit(jax.vmap(obj.network_output, (None, 0)))(setup.params, batch)
    y = eqx.filter_jit(jax.vmap(obj.simulate))(x, batch)
    x_tilde, _ = local_inverse(method.rule, obj, x, y, batch)

    def l1(p):
        xp = jax.vmap(obj.network_output, (None, 0))(p, batch)
        return jnp.sum(jnp.abs(xp - x_tilde)) / 4

    expected = jax.tree.map(lambda p, g: p - g, setup.params, jax.jit(jax.grad(l1))(setup.params))
    new, _, _ = jit_step(method, obj, setup.params, batch)
    for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def toy_reference(rule, steps=10):
    """The book's 2D toy by hand: y = (x₀, x₁²), L = |y|², from (3, 3)."""
    x, path = np.array([3.0, 3.0]), []
    for _ in range(steps):
        if rule == "sgd":
            x = x - 0.01 * np.array([2 * x[0], 4 * x[1] ** 3])
        elif rule == "newton":
            x = x - (1 / 3) * np.array([2 * x[0], 4 * x[1] ** 3]) / np.array([2.0, 12 * x[1] ** 2])
        else:
            y = np.array([x[0], x[1] ** 2]) * (1 - 0.3)
            x = np.array([y[0], np.sqrt(y[1])])
        path.append(x.copy())
    return np.array(path)


@pytest.mark.parametrize("rule", ["sgd", "newton", "sip"])
def test_toy2d_trajectories_equal_hand_written_loops(rule, tmp_path):
    summary = train(make_config("toy2d", rule, budget=Budget(steps=10), settings={"eval_every": 1}), tmp_path)
    rows = [line.split(",") for line in (tmp_path / "metrics.csv").read_text().splitlines()[1:]]
    xs = {int(r[0]): {} for r in rows}
    for step, _, split, metric, value in rows:
        if split == "test" and metric in ("x0", "x1"):
            xs[int(step)][metric] = float(value)
    path = np.array([[xs[k]["x0"], xs[k]["x1"]] for k in range(1, 11)])
    np.testing.assert_allclose(path, toy_reference(rule), rtol=1e-12)
    assert summary["steps"] == 10


def test_toy2d_ordering_after_ten_iterations(tmp_path):
    dist = {
        rule: train(make_config("toy2d", rule, budget=Budget(steps=10)), tmp_path / rule)["final_test_metrics"][
            "x_dist"
        ]
        for rule in ("sgd", "newton", "sip")
    }
    assert dist["sip"] < dist["newton"] < dist["sgd"]  # the book's ordering


def test_no_network_optimises_each_test_sample_directly(tmp_path):
    """exp_inverse without a network: SIP with η = 1 and SGD at lr = b (the proxy is a batch
    mean, so each x_i's gradient carries 1/b) lands on x* in one step."""
    settings = {"no_network": True, "optimizer": "sgd", "lr": 16.0, "n_test": 16, "batch_size": 16, "n_train": 16}
    config = make_config("exp_inverse", "sip", budget=Budget(steps=1), settings=settings)
    setup = build(config)
    step = make_step(setup, 16)
    order = jnp.arange(16)
    params, _, _ = step(setup.params, setup.stages[0].method.init(setup.params), setup.data["train"], order, 0)
    samples = setup.data["train"]["sample"]
    np.testing.assert_allclose(params.x, samples["x_gt"], rtol=1e-5, atol=1e-5)
    assert params.x.shape == (16, 1)
    # three epochs on the same samples: exp_inverse draws fresh training samples each epoch
    # with a network, which without one would swap the targets under their variables
    config = make_config("exp_inverse", "sip", budget=Budget(steps=3), settings=settings)
    assert config.fresh_samples is False
    summary = train(config, tmp_path)
    assert summary["final_test_metrics"]["x_l1"] < 1e-4
    with pytest.raises(ConfigError, match="fresh_samples=true cannot go with no_network"):
        make_config("exp_inverse", "sip", budget=Budget(steps=1), settings={**settings, "fresh_samples": "true"})
    # the library path too: the engine refuses fresh samples for a user's own direct optimisation
    with pytest.raises(ConfigError, match="fresh_samples cannot be on"):
        Steps(setup, Placement(), TrainSettings(fresh_samples=True), 0)
    assert not Steps(setup, Placement(), TrainSettings(), 0).fresh  # the wrapper's default: fixed


def test_no_network_keeps_the_wrapped_problems_float64(tmp_path):
    """heat's physics is float64: without a network the wrapper still asks for x64, so the
    direct optimisation (the SIP paper's heat comparison) runs with x64 off outside (as in
    the CLI; the test suite turns it on) and improves x."""
    settings = {"no_network": True, "resolution": 16, "n_test": 4, "n_train": 4, "batch_size": 4,
                "optimizer": "sgd", "lr": 4.0, "eval_every": 1}  # fmt: skip
    config = make_config("heat", "sip", budget=Budget(steps=3), settings=settings)
    assert build(config).problem.needs_float64
    with jax.enable_x64(False):  # failed with "heat computes in float64" before the wrapper said so
        summary = train(config, tmp_path)
    rows = [line.split(",") for line in (tmp_path / "metrics.csv").read_text().splitlines()[1:]]
    x_l1 = [float(r[4]) for r in rows if r[2] == "test" and r[3] == "x_l1"]
    assert summary["final_test_metrics"]["x_l1"] == pytest.approx(x_l1[-1], rel=1e-6)
    assert x_l1[-1] < 0.9 * x_l1[0]


def test_newton_method_equals_numpy_newton_on_the_toy():
    setup, stage, batch = one_step("toy2d", "newton", {"lr": 1.0})
    new, _, _ = jit_step(stage.method, setup.objective, setup.params, batch)
    x = np.array([3.0, 3.0])
    np.testing.assert_allclose(new.x, x - np.array([2 * x[0], 4 * x[1] ** 3]) / np.array([2.0, 12 * x[1] ** 2]))


# CG on a symmetric positive (semi)definite operator
SPD_CG = {"solver": lx.CG(rtol=0.0, atol=0.0, max_steps=1000), "tags": (lx.symmetric_tag, lx.positive_semidefinite_tag)}


# --- LinearSolve inside the user's own jit, x64 off (issue 33) ----------------------------
UNDER_JIT = """
import json, warnings
import jax, jax.numpy as jnp, numpy as np
import physgrad
import lineax as lx
from physgrad.inverse import LinearSolve
cg, psd = lx.CG(rtol=0.0, atol=0.0, max_steps=1000), (lx.symmetric_tag, lx.positive_semidefinite_tag)

n, b = 32, 8
rng = np.random.default_rng(0)
k = np.fft.rfftfreq(n) * n
decay = np.exp(-0.018 * k**2)                  # heat kernel exp(-κ t k²): eigenvalues in [0.01, 1]
q, _ = np.linalg.qr(rng.normal(size=(n, n)))
matrix = (q * np.logspace(0, np.log10(170.0), n)) @ q.T   # SPD, condition 170

def heat(x, sample):                           # FFT heat diffusion (SPD circulant operator)
    return jnp.fft.irfft(jnp.fft.rfft(x) * jnp.asarray(decay, jnp.float32), n)

def dense(x, sample):
    return jnp.asarray(matrix, jnp.float32) @ x

inverses = {"heat": lambda y: np.fft.irfft(np.fft.rfft(y) / decay, n),
            "dense": lambda y: np.linalg.solve(matrix, y.T).T}
network = lambda params, sample: params["w"] @ sample["y"]
params = {"w": jnp.asarray(0.5 * np.eye(n) + 0.01 * rng.normal(size=(n, n)), jnp.float32)}
y_star = rng.normal(size=(b, n))
batch = {"y": jnp.asarray(y_star, jnp.float32)}
out = {"x64": bool(jax.config.jax_enable_x64)}
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    for name, simulate in (("heat", heat), ("dense", dense)):
        # the reference: x̃ = P⁻¹(y*) in NumPy float64; d = (1/b) Σ_i (x_i − x̃_i) y*_iᵀ
        x = y_star @ np.asarray(params["w"], np.float64).T
        want = (x - inverses[name](y_star)).T @ y_star / b
        for precision in ("float32", "float64"):
            estimate = physgrad.sip(network, simulate, lambda s: s["y"], solver=LinearSolve(cg, tags=psd), precision=precision)
            direction, stats = jax.jit(estimate)(params, batch)
            d = np.asarray(direction["w"], np.float64)
            out[f"{name}_{precision}"] = {"dtype": str(direction["w"].dtype), "failures": int(stats["inverse_failures"]),
                                          "error": float(np.abs(d - want).max() / np.abs(want).max())}
# the run's own warnings (a float64 request truncated, a dtype mix), not a dependency's
# DeprecationWarning (at the version floors one of them calls jax.core.mapped_aval, which jax
# 0.8.2 deprecates: make test-floors failed on it)
out["warnings"] = [str(w.message)[:200] for w in caught if not issubclass(w.category, DeprecationWarning)]
print(json.dumps(out))
"""


@pytest.mark.costly("x64 off needs a fresh interpreter: both simulators at both precisions in a user's jit")
def test_linear_solve_sip_in_float32_and_float64_inside_a_users_jit_with_x64_off(tmp_path):
    """Issue 33: with ``precision="float64"`` lineax's solve used to be lowered after the
    float64 scope closed (dtype errors under jit). Both simulators, both precisions, against
    the NumPy float64 inverse, in a fresh interpreter with JAX's defaults."""
    from test_side_effects import run_fresh

    out = run_fresh(UNDER_JIT, tmp_path)
    assert out["x64"] is False and out["warnings"] == []
    for name in ("heat", "dense"):
        for precision, tolerance in (("float32", 1e-3), ("float64", 1e-5)):
            case = out[f"{name}_{precision}"]
            assert case["dtype"] == "float32" and case["failures"] == 0, (name, precision, case)
            assert case["error"] < tolerance, (name, precision, case)


def test_most_solves_failing_warns_once_and_is_counted():
    """A solve that cannot converge (2 CG steps on a condition-1e6 operator): the count is in
    the stats and one InverseFailureWarning is shown over three jitted steps."""
    import warnings

    import physgrad
    from physgrad.inverse import InverseFailureWarning, LinearSolve

    matrix = jnp.asarray(np.diag(np.logspace(0, 6, 8)), jnp.float32)
    estimate = physgrad.sip(lambda p, s: p @ s, lambda x, s: matrix @ x, lambda s: 2 * s,
                            solver=LinearSolve(**SPD_CG, max_steps=2))  # fmt: skip
    step = jax.jit(estimate)
    params, batch = jnp.eye(8, dtype=jnp.float32), jnp.ones((4, 8), jnp.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for _ in range(3):
            _, stats = step(params, batch)
            jax.block_until_ready(stats)
        jax.effects_barrier()
    assert int(stats["inverse_failures"]) == 4
    assert [w.category for w in caught] == [InverseFailureWarning]
    assert "inverse_failures" in str(caught[0].message)
    quiet = physgrad.sip(lambda p, s: p @ s, lambda x, s: matrix @ x, lambda s: 2 * s,
                         solver=LinearSolve(**SPD_CG, max_steps=2), warn_failures=None)  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        jax.block_until_ready(jax.jit(quiet)(params, batch))
        jax.effects_barrier()
    assert caught == []

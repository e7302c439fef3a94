"""Acceptance tests of a step (physgrad.acceptance, LM's GainRatio) against hand-written
NumPy loops, and a user's own Method with an acceptance in their own jitted loop."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
from physgrad import Method, Objective
from physgrad.acceptance import (
    All,
    FiniteGradient,
    NormBound,
    NormBoundState,
    Proposal,
    SolverSuccess,
    keep_where,
)
from physgrad.methods import GainRatio, Gradient, LevenbergMarquardt, LossAwareDP, MethodState
from physgrad.transforms import norm_guard

# a fixed sequence of gradient norms: warm-up, a spike, a NaN, an infinity, recovery
NORMS = [1.0, 2.0, 0.5, 1e4, 3.0, np.nan, 250.0, np.inf, 1.0, 400.0, 2.0]


def numpy_norm_bound(norms, factor=10.0, decay=0.9, first=100.0):
    """The running bound by hand, in float32 as the state: per step (taken, skip_nan, skip_norm, c after)."""
    c, out = np.float32(0.0), []
    for n in norms:
        finite = math.isfinite(n)
        within = c == 0 or n <= c
        taken = finite and within
        if taken:
            c = np.float32(first * n if c == 0 else decay * float(c) + factor * n)
        out.append((taken, not taken and not finite, not taken and finite and not within, float(c)))
    return out


def proposal(direction, stats=None):
    params = jax.tree.map(jnp.zeros_like, direction)
    return Proposal(None, params, None, direction, direction, direction, stats or {"loss": jnp.float32(0.0)})


def test_all_of_finite_and_norm_bound_follows_the_hand_written_rule():
    acceptance = All(FiniteGradient(), NormBound())
    state = acceptance.init({"g": jnp.zeros(1)})
    judge = jax.jit(acceptance.__call__)
    for n, (taken, nan, norm, bound) in zip(NORMS, numpy_norm_bound(NORMS)):
        accepted, stats, state = judge(proposal({"g": jnp.asarray([n], jnp.float32)}), state)
        assert bool(accepted) == taken, n
        assert {k: float(v) for k, v in stats.items()} == {"skipped": float(not taken), "skip_nan": float(nan),
                                                           "skip_norm": float(norm)}  # fmt: skip
        assert float(state[1].bound) == pytest.approx(bound, rel=1e-6)


def test_norm_guard_transformation_agrees_with_the_norm_bound_test():
    """The optax transformation and the acceptance test share one rule: on finite norms the
    same steps are dropped and the same bound is kept."""
    finite = [n for n in NORMS if math.isfinite(n)]
    guard = norm_guard(optax.sgd(1.0))
    guard_state = guard.init({"g": jnp.zeros(1)})
    test = NormBound()
    test_state = test.init({"g": jnp.zeros(1)})
    for n, (taken, _, _, bound) in zip(finite, numpy_norm_bound(finite)):
        g = {"g": jnp.asarray([n], jnp.float32)}
        updates, guard_state = guard.update(g, guard_state)
        accepted, stats, test_state = test(proposal(g), test_state)
        assert bool(accepted) == taken and float(stats["skip_norm"]) == float(not taken)
        assert float(updates["g"][0]) == (-n if taken else 0.0)
        assert float(guard_state.bound) == float(test_state.bound) == pytest.approx(bound, rel=1e-6)


def test_a_test_that_passes_a_step_another_refuses_keeps_its_state():
    acceptance = All(NormBound(), SolverSuccess())
    state = (NormBoundState(jnp.float32(5.0)), ())
    g = {"g": jnp.asarray([1.0], jnp.float32)}
    accepted, stats, new = acceptance(proposal(g, {"loss": 0.0, "solver_ok": jnp.asarray(False)}), state)
    assert not bool(accepted) and float(stats["skip_solver"]) == 1.0 and float(stats["skip_norm"]) == 0.0
    assert float(new[0].bound) == 5.0  # the step was not taken: the bound learns nothing
    accepted, _, new = acceptance(proposal(g, {"loss": 0.0, "solver_ok": jnp.asarray(True)}), state)
    assert bool(accepted) and float(new[0].bound) == pytest.approx(0.9 * 5.0 + 10.0)


def test_an_unenforced_test_reports_but_never_refuses():
    nan = {"g": jnp.asarray([np.nan], jnp.float32)}
    failed = {"loss": 0.0, "solver_ok": jnp.asarray(False)}
    accepted, stats, _ = All(FiniteGradient(enforce=False), SolverSuccess())(proposal(nan, failed), ((), ()))
    assert not bool(accepted)  # refused for the solver; the gradient was not finite either
    assert float(stats["skip_nan"]) == 1.0 and float(stats["skip_solver"]) == 1.0
    accepted, stats, _ = All(FiniteGradient(enforce=False))(proposal(nan), ((),))
    assert bool(accepted) and float(stats["skipped"]) == 0.0 and float(stats["skip_nan"]) == 0.0
    single = FiniteGradient()  # a test alone: the same statistics, its own state
    accepted, stats, state = single(proposal(nan), single.init(nan))
    assert not bool(accepted) and set(stats) == {"skipped", "skip_nan"} and state == ()


def test_acceptance_refuses_bad_configurations_in_one_line():
    with pytest.raises(ValueError, match="distinct names"):
        All(NormBound(), NormBound(factor=5.0))
    with pytest.raises(ValueError, match="solver_ok"):
        SolverSuccess()(proposal({"g": jnp.ones(1)}), ())


def test_keep_where_takes_the_new_tree_or_keeps_the_old_one():
    new, old = {"a": jnp.ones(3), "b": (jnp.float32(2.0), None)}, {"a": jnp.zeros(3), "b": (jnp.float32(1.0), None)}
    assert float(keep_where(jnp.asarray(True), new, old)["b"][0]) == 2.0
    kept = keep_where(jnp.asarray(False), new, old)
    np.testing.assert_array_equal(kept["a"], np.zeros(3))
    assert kept["b"][1] is None


# --- Levenberg–Marquardt's gain ratio and Nielsen's rule ---------------------------------------


def _sine_problem():
    """y = sin(w x), L = ½ mean (y − t)²: a model the Gauss–Newton step does not fit exactly."""
    rng = np.random.default_rng(0)
    x, t = rng.standard_normal(5), rng.standard_normal(5)

    def predict(p, s):
        return jnp.sin(p["w"] * s["x"])

    def loss(y, s):
        return 0.5 * (y - s["t"]) ** 2

    return Objective(predict, loss), {"x": jnp.asarray(x), "t": jnp.asarray(t)}, x, t


def numpy_gain_ratio(w, delta, x, t):
    """ρ by hand: the actual decrease of the batch loss over −(g u + ½ u²), u = x cos(w x) Δ."""
    loss = lambda w: np.mean(0.5 * (np.sin(w * x) - t) ** 2)  # noqa: E731
    u = x * np.cos(w * x) * delta
    predicted = -np.mean((np.sin(w * x) - t) * u + 0.5 * u**2)
    return (loss(w) - loss(w + delta)) / predicted if predicted > 0 else -np.inf


def numpy_nielsen(mu, nu, rho, lo=1e-12, hi=1e12):
    if math.isfinite(rho) and rho > 0:
        return min(max(mu * max(1 / 3, 1 - (2 * rho - 1) ** 3), lo), hi), 2.0, True
    return min(max(mu * nu, lo), hi), 2 * nu, False


@pytest.mark.parametrize("reject", [True, False])
def test_gain_ratio_follows_nielsens_rule_by_hand_over_a_fixed_sequence_of_steps(reject):
    # (θ, Δ): ρ ≈ 1, a model that predicts no decrease (ρ = −∞), ρ < 0, 0 < ρ < ½, a NaN step
    steps = [(0.3, 0.05), (0.3, -0.4), (2.0, -1.5), (1.0, 1.0), (0.3, 3.0), (2.0, -0.75), (0.3, 0.2), (0.3, np.nan)]
    gain = GainRatio(damping=1e-2, reject=reject)
    with jax.enable_x64(True):
        objective, batch, x, t = _sine_problem()
        state = gain.init({"w": jnp.float64(0.0)})
        mu, nu = 1e-2, 2.0
        for w, delta in steps:
            params = {"w": jnp.float64(w)}
            updates = {"w": jnp.float64(delta)}
            candidate = jax.tree.map(jnp.add, params, updates)
            stats = {"loss": objective.batch_loss(params, batch)}
            accepted, out, state = gain(Proposal(objective, params, batch, updates, updates, candidate, stats), state)
            rho = numpy_gain_ratio(w, delta, x, t)
            mu_used = mu
            mu, nu, ok = numpy_nielsen(mu, nu, rho)
            assert float(out["damping"]) == pytest.approx(mu_used, rel=1e-12)
            if math.isfinite(rho):
                assert float(out["gain_ratio"]) == pytest.approx(rho, rel=1e-9)
            else:
                assert not math.isfinite(float(out["gain_ratio"]))
            assert float(out["accepted"]) == float(ok) and bool(accepted) == (ok or not reject)
            assert float(state.damping) == pytest.approx(mu, rel=1e-12) and float(state.growth) == nu


def test_lm_is_a_composition_with_the_gain_ratio_test():
    lm = LevenbergMarquardt(damping=1e-2, reject=False, max_damping=1.0)
    assert lm.acceptance == GainRatio(1e-2, False, 1e-12, 1.0)
    assert isinstance(lm.method, Method) and not isinstance(lm, Method)
    with pytest.raises(ValueError, match="damping must be positive"):
        LevenbergMarquardt(damping=0.0)


# --- a user's own method and loop -------------------------------------------------------------


def _regression():
    rng = np.random.default_rng(1)
    x = rng.standard_normal((32, 3)).astype(np.float32)
    t = (x @ np.asarray([1.0, -2.0, 0.5], np.float32))[:, None]

    def predict(p, s):
        return p["w"] @ s["x"] + p["b"]

    def loss(y, s):
        return jnp.sum((y - s["t"]) ** 2)

    params = {"w": jnp.zeros((1, 3), jnp.float32), "b": jnp.zeros(1, jnp.float32)}
    return Objective(predict, loss), params, {"x": jnp.asarray(x), "t": jnp.asarray(t)}


def test_a_user_composes_a_method_with_an_optax_chain_and_acceptance_in_their_own_jitted_loop():
    objective, params, batch = _regression()
    chain = optax.chain(optax.clip_by_global_norm(10.0), optax.adam(1e-1))
    method = Method(Gradient(), chain, acceptance=All(FiniteGradient(), NormBound()))
    state = method.init(params)
    assert isinstance(state, MethodState) and float(optax.tree_utils.tree_get(state, "bound")) == 0.0

    @jax.jit
    def step(params, state, batch):
        return method.step(objective, params, state, batch)

    first = float(objective.batch_loss(params, batch))
    for _ in range(100):
        params, state, stats = step(params, state, batch)
        assert float(stats["skipped"]) == 0.0
    assert float(objective.batch_loss(params, batch)) < 0.1 * first
    # a NaN sample: the gradient is not finite, the step is refused and nothing moves
    poisoned = {**batch, "x": batch["x"].at[0, 0].set(jnp.nan)}
    new, new_state, stats = step(params, state, poisoned)
    assert float(stats["skipped"]) == 1.0 and float(stats["skip_nan"]) == 1.0 and float(stats["skip_norm"]) == 0.0
    assert all(
        np.array_equal(a, b) for a, b in zip(jax.tree.leaves((params, state)), jax.tree.leaves((new, new_state)))
    )
    # without an acceptance the state is the optimizer's own, as before
    assert jax.tree.structure(Method(Gradient(), chain).init(params)) == jax.tree.structure(chain.init(params))


def test_a_method_with_acceptance_steps_a_whole_equinox_module():
    model = physgrad.MLP((3, 4, 1), jax.nn.tanh, key=jax.random.key(0))
    objective, _, batch = _regression()
    objective = objective._replace(predict=lambda m, s: m(s["x"]))
    method = Method(Gradient(), optax.sgd(1e-2), acceptance=All(FiniteGradient()))
    new, _, stats = eqx.filter_jit(lambda m, b: method.step(objective, m, method.init(m), b))(model, batch)
    assert float(stats["skipped"]) == 0.0 and new.activation is model.activation


def test_loss_aware_dp_is_a_constructor_of_a_method():
    method = LossAwareDP(Gradient(), optax.sgd(1.0), ("value", "grad"))
    assert type(method) is Method and method.extras == ("value", "grad")
    with pytest.raises(ValueError, match="unknown optimizer extras"):
        LossAwareDP(Gradient(), optax.sgd(1.0), ("hessian",))


def test_the_registry_names_each_method_once():
    from physgrad.harness import registry

    assert list(registry.METHODS) == ["adam", "sgd", "rmsprop", "adagrad", "adadelta", "gn", "hig", "khig", "kgn",
                                      "khig_half", "ekhig", "lm", "kfac", "kfac_hig", "sip", "newton", "bptt", "sbptt_m", "sbptt_c",
                                      "no_temporal", "one", "nog", "wig"]  # fmt: skip
    for name in ("hig", "sip", "bptt", "newton", "lm", "nog"):  # the library's names only
        assert not hasattr(registry, name), name
    assert registry.describe("hig").startswith("Half-inverse gradients")

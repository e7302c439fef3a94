"""The rollout engine and its gradient-flow policies against hand-written references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad  # noqa: F401
from physgrad.rollout import M, N, R, S, closed_loop, cosine, joint_gradients, rollout, sign_mask, value_and_grad

F32 = jnp.float32
A = np.array([[1.0, 0.1, 0.0], [-0.2, 0.95, 0.1], [0.0, -0.1, 0.9]])
B = np.array([[0.0], [0.1], [0.05]])


def nonlinear_system(m=9, weights=None):
    """A small nonlinear closed loop: tanh controller, mildly nonlinear physics, control cost."""

    def control(p, s):
        return jnp.tanh(p["W"] @ s + p["b"])

    def physics(s, c):
        return jnp.asarray(A, F32) @ s + jnp.asarray(B, F32) @ c + 0.05 * jnp.sin(s)

    def step_loss(s, c, k):
        return jnp.sum(s**2) + 0.1 * jnp.sum(c**2) * (1.0 + 0.1 * k)

    w = jnp.linspace(0.5, 1.5, m, dtype=F32) if weights is None else weights
    return closed_loop(control, physics, step_loss, m, w), (control, physics, step_loss, w)


def params_and_states(b=4):
    k1, k2 = jax.random.split(jax.random.key(0))
    params = {"W": 0.5 * jax.random.normal(k1, (1, 3), F32), "b": jnp.array([0.1], F32)}
    return params, jax.random.normal(k2, (b, 3), F32)


def loop_loss(pieces, params, s0, stop_network=False, stop_physics=False, cut=lambda k: False, counts=lambda k: True):
    """The rollout loss as a plain Python loop with explicit stop_gradients (the reference)."""
    control, physics, step_loss, w = pieces
    s, total = s0, 0.0
    for k in range(len(w)):
        if cut(k):
            s = jax.lax.stop_gradient(s)
        s_net = jax.lax.stop_gradient(s) if stop_network else s
        s_phys = jax.lax.stop_gradient(s) if stop_physics else s
        c = jax.vmap(control, (None, 0))(params, s_net)
        s = jax.vmap(physics)(s_phys, c)
        if counts(k):
            total = total + w[k] * jnp.mean(jax.vmap(step_loss, (0, 0, None))(s, c, k))
    return total


def close(a, b, rtol=1e-5, atol=1e-6):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


def test_regular_equals_jax_grad_of_the_plain_rollout_loss():
    system, pieces = nonlinear_system()
    params, s0 = params_and_states()
    loss, grads = jax.jit(lambda p: value_and_grad(system, p, s0, R()))(params)
    ref_loss, ref = jax.value_and_grad(lambda p: loop_loss(pieces, p, s0))(params)
    np.testing.assert_allclose(loss, ref_loss, rtol=1e-6)
    close(grads, ref)


def test_stopped_equals_the_sum_of_one_step_gradients():
    """S: each control gets only the gradient of its own step's loss, states held fixed."""
    system, (control, physics, step_loss, w) = nonlinear_system()
    params, s0 = params_and_states()
    _, grads = jax.jit(lambda p: value_and_grad(system, p, s0, S()))(params)
    states, s = [], s0  # the forward trajectory, then one gradient per step
    for _ in range(len(w)):
        states.append(s)
        s = jax.vmap(physics)(s, jax.vmap(control, (None, 0))(params, s))
    total = jax.tree.map(jnp.zeros_like, params)
    for k, s_k in enumerate(states):

        def one_step(p, s_k=s_k, k=k):
            c = jax.vmap(control, (None, 0))(p, s_k)
            return w[k] * jnp.mean(jax.vmap(step_loss, (0, 0, None))(jax.vmap(physics)(s_k, c), c, k))

        total = jax.tree.map(jnp.add, total, jax.grad(one_step)(params))
    close(grads, total)


def linear_reference(A, B, theta, s0, w, modified):
    """g for s' = A s + B c, c = Θ s, L = Σ_k w_k ½|s_{k+1}|² (batch mean), NumPy float64:
    a_{k+1} = w_k s_{k+1} + J_{k+1}ᵀ a_{k+2} with J = A (M) or A + BΘ (R);
    ∂L/∂Θ = Σ_k (Bᵀ a_{k+1}) s_kᵀ."""
    J = A if modified else A + B @ theta
    grads = np.zeros_like(theta)
    for s in s0:
        traj = [s]
        for _ in range(len(w)):
            traj.append(A @ traj[-1] + B @ (theta @ traj[-1]))
        a_next = np.zeros_like(s)
        for k in reversed(range(len(w))):
            a = w[k] * traj[k + 1] + J.T @ a_next
            grads += np.outer(B.T @ a, traj[k])
            a_next = a
    return grads / len(s0)


@pytest.mark.parametrize("policy,modified", [(M(), True), (R(), False)])
def test_modified_and_regular_equal_hand_written_adjoints_on_a_linear_system(policy, modified):
    theta = np.array([[-0.3, 0.2, -0.1]])
    s0 = np.random.default_rng(1).normal(size=(5, 3))
    w = np.linspace(0.2, 1.0, 7)
    system = closed_loop(
        lambda p, s: p @ s, lambda s, c: jnp.asarray(A) @ s + jnp.asarray(B) @ c,
        lambda s, c, k: 0.5 * jnp.sum(s**2), len(w), jnp.asarray(w),
    )  # fmt: skip
    _, g = value_and_grad(system, jnp.asarray(theta), jnp.asarray(s0), policy)
    np.testing.assert_allclose(np.asarray(g), linear_reference(A, B, theta, s0, w, modified), rtol=1e-10)
    _, g_m, g_r = joint_gradients(system, jnp.asarray(theta), jnp.asarray(s0), M(), R())
    np.testing.assert_allclose(
        np.asarray(g_m if modified else g_r), linear_reference(A, B, theta, s0, w, modified), rtol=1e-10
    )


@pytest.mark.parametrize(
    "policy,kwargs",
    [
        (N(), dict(stop_physics=True)),
        (R(truncate=3), dict(cut=lambda k: k > 0 and k % 3 == 0)),
        (M(warmup=4), dict(stop_network=True, cut=lambda k: k == 4, counts=lambda k: k >= 4)),
        (R(truncate=4, warmup=2), dict(cut=lambda k: k == 2 or (k > 0 and k % 4 == 0), counts=lambda k: k >= 2)),
    ],
)
def test_other_policies_equal_their_loops(policy, kwargs):
    system, pieces = nonlinear_system()
    params, s0 = params_and_states()
    loss, grads = jax.jit(lambda p: value_and_grad(system, p, s0, policy))(params)
    ref_loss, ref = jax.value_and_grad(lambda p: loop_loss(pieces, p, s0, **kwargs))(params)
    np.testing.assert_allclose(loss, ref_loss, rtol=1e-6)
    close(grads, ref)


def test_forward_pass_is_identical_under_every_policy():
    system, _ = nonlinear_system()
    params, s0 = params_and_states()
    values = [rollout(system, params, s0, p, keep_states=True) for p in (R(), M(), N(), S())]
    for loss, states in values[1:]:
        np.testing.assert_array_equal(loss, values[0][0])
        np.testing.assert_array_equal(states, values[0][1])


@pytest.mark.parametrize("checkpoint", [False, True])
@pytest.mark.parametrize("base", [M(), S(), N(), M(truncate=3), R(warmup=2)])
def test_one_pass_joint_gradients_equal_two_passes(base, checkpoint):
    system, _ = nonlinear_system()
    params, s0 = params_and_states()

    @jax.jit  # one program per case: the two-pass references alongside (eagerly, each scan compiles on its own)
    def gradients(p):
        joint = joint_gradients(system, p, s0, base, R(), checkpoint=checkpoint)
        return joint, value_and_grad(system, p, s0, R()), value_and_grad(system, p, s0, base)[1]

    (loss, g_base, g_r), (l_r, ref_r), ref_base = gradients(params)
    np.testing.assert_allclose(loss, l_r, rtol=1e-6)
    close(g_base, ref_base)
    close(g_r, ref_r)


@pytest.mark.parametrize("checkpoint", [False, True])
def test_joint_gradients_with_an_integer_leaf_in_the_state(checkpoint):
    """A state carrying an integer leaf (a time-stepper sample's solver ``index``) has no
    adjoint for it: the one-pass joint gradients equal the two plain passes (JAX's own
    handling of integer inputs), and the index still acts on the physics."""

    def control(p, s):
        return jnp.tanh(p["W"] @ s["u"] + p["b"])

    def physics(s, c):
        rate = 1.0 + 0.1 * s["index"].astype(F32)  # the integer leaf selects the dynamics
        return {"u": rate * (jnp.asarray(A, F32) @ s["u"]) + jnp.asarray(B, F32) @ c, "index": s["index"]}

    system = closed_loop(control, physics, lambda s, c, k: jnp.sum(s["u"] ** 2) + 0.1 * jnp.sum(c**2), 6,
                         jnp.linspace(0.5, 1.5, 6, dtype=F32))  # fmt: skip
    params, u0 = params_and_states()
    s0 = {"u": u0, "index": jnp.arange(4, dtype=jnp.int32)}

    @jax.jit
    def gradients(p):
        return joint_gradients(system, p, s0, M(), R(), checkpoint=checkpoint), value_and_grad(
            system, p, s0, R()), value_and_grad(system, p, s0, M())[1]  # fmt: skip

    (loss, g_m, g_r), (l_r, ref_r), ref_m = gradients(params)
    np.testing.assert_allclose(loss, l_r, rtol=1e-6)
    close(g_m, ref_m)
    close(g_r, ref_r)
    assert not np.allclose(np.asarray(g_r["W"]), np.asarray(ref_m["W"]))  # the two flows differ here


def test_combined_is_the_sign_masked_modified_gradient():
    system, _ = nonlinear_system()
    params, s0 = params_and_states()
    _, g_m = value_and_grad(system, params, s0, M())
    _, g_r = value_and_grad(system, params, s0, R())
    g_c = sign_mask(g_m, g_r)
    for c, m_, r in zip(*(jax.tree.leaves(t) for t in (g_c, g_m, g_r))):
        c, m_, r = map(np.asarray, (c, m_, r))
        expect = np.where(np.sign(m_) == np.sign(r), m_, 0.0)
        np.testing.assert_array_equal(c, expect)
    assert float(sum(jnp.vdot(a, b) for a, b in zip(jax.tree.leaves(g_c), jax.tree.leaves(g_r)))) >= 0.0
    # ties: sign(0) = 0, so a zero in the comparison drops the component
    masked = sign_mask({"x": jnp.array([1.0, -2.0, 3.0, 0.0])}, {"x": jnp.array([2.0, 1.0, 0.0, 0.0])})
    np.testing.assert_array_equal(masked["x"], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(cosine({"a": jnp.array([1.0, 0.0])}, {"a": jnp.array([1.0, 1.0])}), 2**-0.5, rtol=1e-6)


def test_checkpointing_changes_memory_not_values():
    m = 240

    def control(p, s):
        return jnp.tanh(p["W2"] @ jnp.tanh(p["W1"] @ s))

    system = closed_loop(
        control, lambda s, c: s + 0.01 * jnp.tanh(c), lambda s, c, k: jnp.sum(s**2), m, jnp.ones(m, F32) / m
    )
    k1, k2, k3 = jax.random.split(jax.random.key(2), 3)
    params = {"W1": 0.1 * jax.random.normal(k1, (64, 8), F32), "W2": 0.1 * jax.random.normal(k2, (8, 64), F32)}
    s0 = jax.random.normal(k3, (16, 8), F32)
    outputs, memory = [], []
    for checkpoint in (False, True):
        f = jax.jit(lambda p, ck=checkpoint: value_and_grad(system, p, s0, R(), checkpoint=ck))
        outputs.append(f(params))
        memory.append(f.lower(params).compile().memory_analysis().temp_size_in_bytes)
    close(outputs[0], outputs[1], rtol=1e-5, atol=1e-6)  # float32: rematerialisation reorders sums
    assert memory[1] < memory[0] / 5, memory
    g = jax.jit(lambda p: joint_gradients(system, p, s0, M(), R(), checkpoint=True))(params)
    close(g[2], outputs[0][1], rtol=1e-5, atol=1e-6)


def test_stop_gradient_paths_never_differentiate_a_stopped_physics():
    """Under S and N the physics input is stopped statically: a simulator whose derivative
    raises still trains (the no-temporal-gradient modality never calls the solver's VJP)."""

    @jax.custom_vjp
    def solver(s):
        return 0.9 * s

    def fwd(s):
        return solver(s), None

    def bwd(_, g):
        raise RuntimeError("this solver has no derivative")

    solver.defvjp(fwd, bwd)

    def physics(s, c):  # the gradient w.r.t. c is needed, the solver's never under S
        return solver(s) + c

    def loss(s, c, k):
        return jnp.sum(s**2)

    theta, s0, w = jnp.array(0.5, F32), jnp.ones((2, 3), F32), jnp.ones(4, F32)
    _, g = value_and_grad(closed_loop(lambda p, s: p * s, physics, loss, 4, w), theta, s0, S())
    assert np.isfinite(float(g)) and float(g) != 0.0
    with pytest.raises(RuntimeError, match="no derivative"):  # R does differentiate the physics
        value_and_grad(closed_loop(lambda p, s: p * s, physics, loss, 4, w), theta, s0, R())

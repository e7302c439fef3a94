"""The rollout engine: s_{k+1} = step(s_k, network(s_k)) over m steps with ``lax.scan``.

One engine serves closed-loop control (stabilised BPTT) and neural time-steppers
(unrolling). A rollout is described by a :class:`System` over a batch of states::

    transition(params, s_network, s_physics, k) -> (s_{k+1}, ℓ_k)

where ``s_network`` is the state as the network sees it and ``s_physics`` as the physics
sees it (the same values; a :class:`~physgrad.rollout.GradientFlow` policy decides which
of them carry gradient), and ℓ_k is the batch-mean loss term of step k. The rollout loss is

    L = Σ_{k<m} w_k · mask_k · ℓ_k,

with per-step weights w (a final-state loss has w = (0, …, 0, 1)) and the policy's mask
(0 inside a warm-up).

Gradients:

- :func:`value_and_grad`: ``jax.value_and_grad`` of L under one policy. With
  ``checkpoint=True`` the scan is rematerialised in two levels (segments of ≈ √m steps):
  the backward pass stores ≈ 2√m states instead of every step's intermediates.
- :func:`joint_gradients`: the gradients of two policies (stabilised BPTT's M and R) from
  **one** forward rollout and **one** backward scan that carries both adjoints,

      λ^P_k = keep_net^P(k) · λ^P_{k+1}·∂T/∂s_net + keep_phys^P(k) · λ^P_{k+1}·∂T/∂s_phys
              + w_k mask^P_k ∂ℓ_k/∂s,
      g^P  = Σ_k (λ^P_{k+1}·∂T/∂θ + w_k mask^P_k ∂ℓ_k/∂θ),

  where each step's linearisation (the VJP of T at (θ, s_k, s_k)) is computed once and
  applied to both cotangents. The forward pass keeps each step's VJP residuals (the
  parameters once, not per step); with ``checkpoint=True`` it keeps only the states and
  the backward scan recomputes each step's VJP (memory ≈ m states). Against the authors'
  two full passes it measured 0.49–0.69× the time and about half the memory on the three
  StableBPTT problems (benchmarks/rollout_step.py).

Internal module: the public names are those :mod:`physgrad.rollout` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from .. import loops
from ..jacobian import float0_zeros, has_tangent
from .policy import GradientFlow, R

Transition = Callable[[PyTree, PyTree, PyTree, Array], tuple[PyTree, Array]]


class System(NamedTuple):
    """A rollout over a batch: ``transition``, its number of steps and per-step weights (m,).

    ``init(batch) -> s0`` turns a batch of samples into the initial state (None: the batch
    is the state). ``differentiable_physics`` is False when the physics inside the
    transition cannot be differentiated (a policy must then stop its input statically).
    """

    transition: Transition
    num_steps: int
    weights: Array
    init: Callable[[PyTree], PyTree] | None = None
    differentiable_physics: bool = True

    def initial_state(self, batch):
        return batch if self.init is None else self.init(batch)


def closed_loop(
    control: Callable[[PyTree, PyTree], PyTree],
    physics: Callable[[PyTree, PyTree], PyTree],
    step_loss: Callable[[PyTree, PyTree, Array], Array],
    num_steps: int,
    weights: Array,
) -> System:
    """A closed-loop control system from per-sample pieces (vmapped over the batch here):

    ``control(params, s) -> c``, ``physics(s, c) -> s'`` and ``step_loss(s', c, k) -> ℓ``;
    the transition is c_k = control(θ, s_net), s_{k+1} = physics(s_phys, c_k) and ℓ_k the
    batch mean of ``step_loss(s_{k+1}, c_k, k)``.
    """

    def transition(params, s_network, s_physics, k):
        c = jax.vmap(control, in_axes=(None, 0))(params, s_network)
        s_next = jax.vmap(physics)(s_physics, c)
        return s_next, jnp.mean(jax.vmap(step_loss, in_axes=(0, 0, None))(s_next, c, k))

    return System(transition, num_steps, jnp.asarray(weights))


def _segment_length(m: int) -> int:
    """The divisor of m closest to √m (two-level checkpointing needs equal segments)."""
    divisors = [d for d in range(1, m + 1) if m % d == 0]
    return min(divisors, key=lambda d: abs(d - math.sqrt(m)))


def _scan(body, carry, steps: Array, checkpoint: bool):
    """``lax.scan(body, carry, steps)``, rematerialised in segments of ≈ √m when asked."""
    if not checkpoint:
        return loops.scan(body, carry, steps)
    m = steps.shape[0]
    length = _segment_length(m)
    inner = jax.checkpoint(body)

    @jax.checkpoint
    def segment(c, ks):
        return loops.scan(inner, c, ks)

    carry, ys = loops.scan(segment, carry, steps.reshape(m // length, length))
    return carry, jax.tree.map(lambda y: y.reshape(m, *y.shape[2:]), ys)


def rollout(
    system: System,
    params: PyTree,
    s0: PyTree,
    policy: GradientFlow | None = None,
    *,
    checkpoint: bool = False,
    keep_states: bool = False,
    keep_final: bool = False,
) -> tuple[Any, ...]:
    """The rollout loss L (and, with ``keep_states``, the states s_1..s_m stacked on a
    leading time axis; with ``keep_final`` also the final state as a third value) from a
    batch of initial states ``s0``, under ``policy`` (default R)."""
    policy = policy or R()
    steps = jnp.arange(system.num_steps)

    def body(carry, k):
        s, total = carry
        s_network, s_physics = policy.inputs(s, k)
        s_next, step_loss = system.transition(params, s_network, s_physics, k)
        total = total + (system.weights[k] * policy.loss_mask(k) * step_loss).astype(total.dtype)
        return (s_next, total), (s_next if keep_states else None)

    (final, loss), states = _scan(body, (s0, jnp.zeros((), system.weights.dtype)), steps, checkpoint)
    return (loss, states, final) if keep_final else (loss, states)


def value_and_grad(
    system: System,
    params,
    s0,
    policy: GradientFlow | None = None,
    *,
    checkpoint: bool = False,
    has_aux: bool = False,
):
    """``(L, ∂L/∂θ)`` under one gradient-flow policy (the forward value is the same for all).

    With ``has_aux`` the value is ``(L, s_m)``, the final state (e.g. to read solver-failure
    flags carried in it)."""

    def loss(p):
        value, _, final = rollout(system, p, s0, policy, checkpoint=checkpoint, keep_final=True)
        return (value, jax.lax.stop_gradient(final)) if has_aux else value

    return jax.value_and_grad(loss, has_aux=has_aux)(params)


def joint_gradients(
    system: System,
    params,
    s0,
    base: GradientFlow,
    comparison: GradientFlow,
    *,
    checkpoint: bool = False,
):
    """``(L, g_base, g_comparison)`` from one forward rollout and one backward scan that
    carries both adjoints (see the module docstring). L is the comparison policy's loss.
    Integer or boolean leaves of the state (or of ``params``) have no adjoint; their entries
    of the gradients are float32 zeros, not JAX's float0 (see :func:`_pair`)."""
    steps = jnp.arange(system.num_steps)

    def linearise(s, k):
        return jax.vjp(lambda p, a, b: system.transition(p, a, b, k), params, s, s)

    # A step's pullback holds its residuals; the parameters among them are the same at
    # every step, so they are kept once (outside the scan), not stacked m times.
    param_leaves = jax.tree.leaves(params)
    layout = {}

    def split(pullback):
        leaves, layout["treedef"] = jax.tree.flatten(pullback)
        layout["shared"] = [next((i for i, p in enumerate(param_leaves) if leaf is p), None) for leaf in leaves]
        return [leaf for leaf, shared in zip(leaves, layout["shared"]) if shared is None]

    def join(stepwise):
        stepwise = iter(stepwise)
        leaves = [next(stepwise) if i is None else param_leaves[i] for i in layout["shared"]]
        return jax.tree.unflatten(layout["treedef"], leaves)

    def forward(s, k):
        (s_next, step_loss), pullback = linearise(s, k)
        return s_next, (step_loss, s if checkpoint else split(pullback))

    _, (step_losses, saved) = loops.scan(forward, s0, steps)
    masks = jax.vmap(lambda k: jnp.stack([base.loss_mask(k) * jnp.ones(()), comparison.loss_mask(k) * jnp.ones(())]))(
        steps
    )
    # (m, 2): w_k · mask_k for (base, comparison), in the dtype of the step losses
    weights = (system.weights[:, None] * masks).astype(step_losses.dtype)
    loss = jnp.sum(weights[:, 1] * step_losses).astype(system.weights.dtype)

    def backward(carry, inputs):
        adjoints, grads = carry  # both stacked on a leading axis of 2: (base, comparison)
        k, w, step_saved = inputs
        pullback = linearise(step_saved, k)[1] if checkpoint else join(step_saved)
        g_params, g_network, g_physics = _pair(pullback, adjoints, w, s0)
        keep = jnp.array([base.keeps(k), comparison.keeps(k)], jnp.float32)  # (2, [net, phys])

        def propagate(a, b):
            shape = (2,) + (1,) * (a.ndim - 1)
            return keep[:, 0].reshape(shape) * a + keep[:, 1].reshape(shape) * b

        adjoints = jax.tree.map(propagate, g_network, g_physics)
        grads = jax.tree.map(jnp.add, grads, g_params)
        return (adjoints, grads), None

    pair = lambda tree: jax.tree.map(lambda a: jnp.zeros((2,) + jnp.shape(a), _adjoint_dtype(a)), tree)  # noqa: E731
    init = (pair(s0), pair(params))
    (_, grads), _ = loops.scan(backward, init, (steps, weights, saved), reverse=True)
    g_base = jax.tree.map(lambda g: g[0], grads)
    g_comparison = jax.tree.map(lambda g: g[1], grads)
    return loss, g_base, g_comparison


def _pair(pullback, adjoints, w, s0):
    """A step's pullback applied to both cotangents (stacked on a leading axis of 2).

    Two calls of the same pullback, not ``vmap``: on CPU the vmapped (batched) transpose
    measured ~1.5× slower than two plain ones (benchmarks/rollout_step.py). A state's integer
    or boolean leaves (a time-stepper sample's solver ``index``) have no adjoint: JAX takes and
    returns a float0 cotangent for them, which cannot be added or carried through a scan, so the
    carry holds float32 zeros in their place (:func:`_adjoint_dtype`) and they are swapped at
    the pullback's door."""

    def cotangent(i):
        return jax.tree.map(lambda a, like: a[i] if has_tangent(like) else float0_zeros(like), adjoints, s0)

    def stack(a, b):
        if a.dtype == jax.dtypes.float0:  # an integer input's cotangent: zeros, as the carry holds them
            return jnp.zeros((2,) + a.shape, jnp.float32)
        return jnp.stack([a, b])

    return jax.tree.map(stack, pullback((cotangent(0), w[0])), pullback((cotangent(1), w[1])))


def _adjoint_dtype(a):
    """The dtype of ``a``'s adjoint in the backward scan's carry: its own where it is inexact,
    float32 zeros for an integer or boolean leaf (see :func:`_pair`)."""
    return jnp.result_type(a) if has_tangent(a) else jnp.float32

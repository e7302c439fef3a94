"""Back-propagation through time with gradient-flow policies, and stabilised BPTT.

Schnell & Thuerey, "Stabilizing Backpropagation Through Time to Learn Complex Physics",
ICLR 2024 (shared/papers/stablebptt.md §1). For a closed loop c_k = N_θ(s_k),
s_{k+1} = P(s_k, c_k) with loss L = Σ_k w_k ℓ_k:

- ``bptt`` (R): the true gradient g_R, adjoint λ_k = λ_{k+1}(∂P/∂s + ∂P/∂c ∂N/∂s) + ∂ℓ_k/∂s;
- ``sbptt_m`` (M): stop-gradient on the network's input, λ̃_k = λ̃_{k+1} ∂P/∂s + ∂ℓ_k/∂s;
- ``no_temporal`` (S): stop-gradient on both paths: each control gets only its one-step
  gradient;
- ``sbptt_c`` (C, the paper's method): g_C = where(sign g_M = sign g_R, g_M, 0) per element.

Each gradient then goes through clipping (``clip=value``: element-wise to ±1, Keras
``clipvalue``; ``norm``: global L2 norm ≤ 1, Keras ``global_clipnorm``; ``none``) and Adam
(lr 1e-3, ε 1e-7, Keras defaults), chained as optax transformations, clipping after the
combination as in the authors' code. Logged per step (averaged per evaluation window):
``grad_norm2``, the squared L2 norm of the gradient before clipping (g_C for C), and for C
``cos_mr``, the cosine between g_M and g_R.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

from ..rollout import Combined, GradientFlow, M, R, S, cosine, joint_gradients, sign_mask, value_and_grad
from .base import AbstractMethod

CLIP_MODES = ("value", "norm", "none")


def clipping(mode: str, threshold: float) -> optax.GradientTransformation:
    """The authors' clip modes as optax transformations (applied before the optimizer)."""
    if mode not in CLIP_MODES:
        raise ValueError(f"unknown clip mode {mode!r}; valid choices: {', '.join(CLIP_MODES)}")
    if threshold <= 0:
        raise ValueError(f"clip_threshold must be positive, got {threshold}")
    return {"value": optax.clip(threshold), "norm": optax.clip_by_global_norm(threshold), "none": optax.identity()}[mode]


class RolloutGradient(AbstractMethod):
    """A gradient of the rollout loss under a gradient-flow policy (or the C combination),
    applied by an optax optimizer."""

    policy: GradientFlow | Combined
    optimizer: optax.GradientTransformation = eqx.field(static=True)
    checkpoint: bool = eqx.field(static=True, default=False)

    def init(self, params):
        return self.optimizer.init(params)

    def check(self, objective):
        if objective.rollout is None:
            raise ValueError(
                "this method back-propagates through a rollout; use a closed-loop problem "
                "(cartpole, guidance, quantum_control)"
            )
        differentiates_physics = isinstance(self.policy, Combined) or not self.policy.stop_physics
        if differentiates_physics and not objective.rollout.differentiable_physics:
            raise ValueError("this method differentiates through the solver, which is not differentiable; use no_temporal")

    def gradient(self, system, params, s0):
        """(loss, gradient, extra statistics) of one batch of initial states."""
        policy = self.policy
        if not isinstance(policy, Combined):
            loss, grads = value_and_grad(system, params, s0, policy, checkpoint=self.checkpoint)
            return loss, grads, {}
        if policy.one_pass:
            loss, g_base, g_comparison = joint_gradients(
                system, params, s0, policy.base, policy.comparison, checkpoint=self.checkpoint
            )
        else:  # the authors' way: two full forward+backward passes
            _, g_base = value_and_grad(system, params, s0, policy.base, checkpoint=self.checkpoint)
            loss, g_comparison = value_and_grad(system, params, s0, policy.comparison, checkpoint=self.checkpoint)
        return loss, sign_mask(g_base, g_comparison), {"cos_mr": cosine(g_base, g_comparison)}

    def step(self, objective, params, state, batch):
        system = objective.rollout
        loss, grads, stats = self.gradient(system, params, system.initial_state(batch))
        norm2 = sum(jnp.vdot(g, g).real for g in jax.tree.leaves(grads))
        updates, state = self.optimizer.update(grads, state, params)
        return optax.apply_updates(params, updates), state, {"loss": loss, "grad_norm2": norm2, **stats}


def _method(policy, clip, clip_threshold, lr, eps, checkpoint):
    optimizer = optax.chain(clipping(clip, clip_threshold), optax.adam(lr, eps=eps))
    return RolloutGradient(policy, optimizer, checkpoint)


def bptt(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
         truncate: int = 0, warmup: int = 0, checkpoint: bool = False):  # fmt: skip
    """Full BPTT (R): the true rollout gradient, clipped, Adam; truncate=k cuts every k steps."""
    return _method(R(truncate=truncate, warmup=warmup), clip, clip_threshold, lr, eps, checkpoint)


def sbptt_m(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
            truncate: int = 0, warmup: int = 0, checkpoint: bool = False):  # fmt: skip
    """Stabilised BPTT's modified gradient (M): stop-gradient on the network's input only."""
    return _method(M(truncate=truncate, warmup=warmup), clip, clip_threshold, lr, eps, checkpoint)


def no_temporal(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
                warmup: int = 0, checkpoint: bool = False):  # fmt: skip
    """No temporal gradient (S): stop-gradient on network and physics inputs (one-step gradients)."""
    return _method(S(warmup=warmup), clip, clip_threshold, lr, eps, checkpoint)


def sbptt_c(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
            one_pass: bool = True, checkpoint: bool = False):  # fmt: skip
    """Stabilised BPTT (C, Schnell & Thuerey 2024): M's gradient masked by the signs of R's."""
    return _method(Combined(M(), R(), one_pass=one_pass), clip, clip_threshold, lr, eps, checkpoint)

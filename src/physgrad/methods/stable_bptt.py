"""Back-propagation through time with gradient-flow policies, and stabilised BPTT.

Schnell & Thuerey, "Stabilizing Backpropagation Through Time to Learn Complex Physics",
ICLR 2024 (§3). For a closed loop c_k = N_θ(s_k), s_{k+1} = P(s_k, c_k) with loss
L = Σ_k w_k ℓ_k:

- R (regular BPTT): the true gradient g_R, adjoint λ_k = λ_{k+1}(∂P/∂s + ∂P/∂c ∂N/∂s) + ∂ℓ_k/∂s;
- M (modified): stop-gradient on the network's input, λ̃_k = λ̃_{k+1} ∂P/∂s + ∂ℓ_k/∂s;
- S (no temporal gradient): stop-gradient on both paths, each control gets only its
  one-step gradient;
- C (stabilised BPTT, the paper's method): g_C = where(sign g_M = sign g_R, g_M, 0) per
  element.

The policy is an object (:mod:`physgrad.rollout.policy`), like diffrax's ``adjoint=``; the
paper applies the result with clipping (Keras ``clipvalue=1`` or ``global_clipnorm=1``) and
Adam (lr 1e-3, ε 1e-7), which any optax chain expresses. Statistics: ``grad_norm2``, the
squared L2 norm of the direction before the optimizer, and for C ``cos_mr``, the cosine
between g_M and g_R.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..rollout import Combined, GradientFlow, M, R, cosine, joint_gradients, sign_mask, value_and_grad
from .base import ROLLOUT, AbstractRule, Estimator, Objective, Part


class RolloutGradient(AbstractRule):
    """The gradient of the rollout loss under a gradient-flow policy, or the C combination
    of two policies (:class:`~physgrad.rollout.Combined`)."""

    policy: GradientFlow | Combined = R()
    checkpoint: bool = eqx.field(static=True, default=False)

    @property
    def part(self) -> Part:  # pyright: ignore[reportIncompatibleVariableOverride]
        """The rollout system; differentiated through its physics unless the policy stops
        the gradient there (S, and M's and R's ``stop_physics``)."""
        differentiates_physics = isinstance(self.policy, Combined) or not self.policy.stop_physics
        return ROLLOUT._replace(differentiable=differentiates_physics)

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

    def __call__(self, objective, params, batch):
        system = objective.rollout
        loss, grads, stats = self.gradient(system, params, system.initial_state(batch))
        norm2 = sum(jnp.vdot(g, g).real for g in jax.tree.leaves(grads))
        return grads, {"loss": loss, "grad_norm2": norm2, **stats}


def bptt(system, *, policy: GradientFlow = R(), checkpoint: bool = False) -> Estimator:
    """The rollout gradient under a gradient-flow policy: ``(params, batch) -> (g, stats)``.

    Arguments:
        system: a :class:`physgrad.rollout.System` (e.g. :func:`physgrad.rollout.closed_loop`);
            a batch is a batch of initial states (or samples, with ``system.init``).
        policy: ``R()`` full BPTT (default), ``M()``, ``S()`` (no temporal gradient), with
            ``truncate=k`` / ``warmup=W`` cuts; or ``Combined(...)``.
        checkpoint: rematerialise the rollout (memory ≈ √m states).
    """
    return Estimator(RolloutGradient(policy, checkpoint), Objective(rollout=system))


def stabilised_bptt(system, *, one_pass: bool = True, checkpoint: bool = False) -> Estimator:
    """Stabilised BPTT (C, Schnell & Thuerey 2024): M's gradient where its sign agrees with
    R's, else 0. ``one_pass`` computes both from one forward and one joint backward pass
    (the authors ran two full passes: ``one_pass=False``). Statistics add ``cos_mr``."""
    return Estimator(RolloutGradient(Combined(M(), R(), one_pass=one_pass), checkpoint), Objective(rollout=system))

"""Rollouts through time: one engine (``lax.scan``), gradient-flow policies, and the
stabilised-BPTT combination. See :mod:`physgrad.rollout.engine` and
:mod:`physgrad.rollout.policy`."""

from .engine import System, closed_loop, joint_gradients, rollout, value_and_grad
from .policy import Combined, GradientFlow, M, N, R, S, cosine, sign_mask

__all__ = [
    "Combined",
    "GradientFlow",
    "M",
    "N",
    "R",
    "S",
    "System",
    "closed_loop",
    "cosine",
    "joint_gradients",
    "rollout",
    "sign_mask",
    "value_and_grad",
]

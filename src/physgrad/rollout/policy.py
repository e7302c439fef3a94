"""Gradient-flow policies: where a rollout's backward pass is cut.

A closed-loop rollout feeds the state s_k into two paths (Schnell & Thuerey, ICLR 2024):

- the **control path** s_k → network → c_k → step, and
- the **physics path** s_k → step directly.

A policy decides, per step k, whether ``stop_gradient`` is applied to the state on either
path, and which per-step losses count. The forward pass is identical under every policy;
only the backward pass differs. Like diffrax's ``adjoint=``, the policy is one argument of
the rollout (:func:`physgrad.rollout.rollout`).

=================  =====================  ======================  ===========================
name               network input          physics input           gradient
=================  =====================  ======================  ===========================
``R`` (regular)    s_k                    s_k                     true BPTT gradient g_R
``M`` (modified)   stop(s_k)              s_k                     g_M: adjoint only through ∂P/∂s
``N``              s_k                    stop(s_k)               adjoint only through the network
``S`` (stopped)    stop(s_k)              stop(s_k)               no temporal gradient (one-step)
=================  =====================  ======================  ===========================

Two cuts combine with any of them (List et al., CMAME 2025, the unrolling study's truncation
and warm-up options):
``truncate=k`` stops both paths at every k-th step, counted from step 0 (truncated BPTT:
gradients live within windows of k steps; with a warm-up the windows are not shifted), ``warmup=W`` runs the first W steps without gradient and drops their
losses (the "pushforward" trick): both paths are stopped at step W and the losses of
steps 0..W−1 are masked.

Internal module: the public names are those :mod:`physgrad.rollout` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp


class GradientFlow(eqx.Module):
    """Where the backward pass of a rollout is cut (see the module docstring).

    ``stop_network`` / ``stop_physics`` apply at every step and are static, so a stopped
    path is never differentiated at all (a solver that cannot be differentiated still
    trains under ``S``). ``truncate`` and ``warmup`` are cuts at particular steps.
    """

    stop_network: bool = eqx.field(static=True, default=False)
    stop_physics: bool = eqx.field(static=True, default=False)
    truncate: int = eqx.field(static=True, default=0)
    warmup: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        if self.truncate < 0 or self.warmup < 0:
            raise ValueError(f"truncate and warmup must be >= 0, got {self.truncate} and {self.warmup}")

    def cut(self, k) -> jax.Array | Literal[False]:
        """Whether both paths are stopped at step ``k`` (a traced bool, or False)."""
        cut = False
        if self.truncate:
            cut = (k > 0) & (k % self.truncate == 0)
        if self.warmup:
            cut = (k == self.warmup) | cut
        return cut

    def loss_mask(self, k) -> jax.Array | float:
        """1 where step k's loss counts, 0 inside the warm-up."""
        return (k >= self.warmup).astype(jnp.float32) if self.warmup else 1.0

    def inputs(self, s, k):
        """The state as the network sees it and as the physics sees it at step ``k``."""
        cut = self.cut(k)
        if cut is not False:
            s = jax.tree.map(lambda a: jnp.where(cut, jax.lax.stop_gradient(a), a), s)
        s_network = jax.lax.stop_gradient(s) if self.stop_network else s
        s_physics = jax.lax.stop_gradient(s) if self.stop_physics else s
        return s_network, s_physics

    def keeps(self, k):
        """Per-step multipliers (network path, physics path) of the adjoint, for the joint
        backward pass: 0 where the path is stopped at step ``k``, else 1."""
        cut = self.cut(k)
        through = 1.0 if cut is False else 1.0 - cut.astype(jnp.float32)
        return (0.0 if self.stop_network else through), (0.0 if self.stop_physics else through)


def R(**cuts) -> GradientFlow:
    """Regular BPTT: the true gradient."""
    return GradientFlow(**cuts)


def M(**cuts) -> GradientFlow:
    """Modified: stop-gradient on the network's input only (the physics path stays)."""
    return GradientFlow(stop_network=True, **cuts)


def N(**cuts) -> GradientFlow:
    """Stop-gradient on the physics input only (the adjoint runs through the network)."""
    return GradientFlow(stop_physics=True, **cuts)


def S(**cuts) -> GradientFlow:
    """Stopped: no temporal gradient; each control gets only its one-step gradient."""
    return GradientFlow(stop_network=True, stop_physics=True, **cuts)


class Combined(eqx.Module):
    """Stabilised BPTT's ``C``: the base gradient (M) masked by the comparison's (R) signs.

        g_C[i] = g_M[i]  if sign(g_M[i]) == sign(g_R[i])  else 0        (sign(0) = 0)

    Magnitudes come from the base; the comparison only supplies signs, so every kept
    component agrees in sign with the true gradient and ⟨g_C, g_R⟩ ≥ 0: −g_C is never an
    ascent direction (the paper's argument for C). ``one_pass`` computes both
    gradients from one forward rollout and one backward pass carrying both adjoints
    (:func:`physgrad.rollout.joint_gradients`); otherwise two full passes, as the authors.
    """

    base: GradientFlow = GradientFlow(stop_network=True)
    comparison: GradientFlow = GradientFlow()
    one_pass: bool = eqx.field(static=True, default=True)


def sign_mask(base, comparison):
    """``where(sign(base) == sign(comparison), base, 0)`` on every leaf."""
    return jax.tree.map(lambda b, c: jnp.where(jnp.sign(b) == jnp.sign(c), b, jnp.zeros_like(b)), base, comparison)


def cosine(a, b) -> jax.Array:
    """Cosine similarity of two pytrees flattened into vectors (0 if either is zero)."""
    dot = sum(jnp.vdot(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    na = jnp.sqrt(sum(jnp.vdot(x, x) for x in jax.tree.leaves(a)))
    nb = jnp.sqrt(sum(jnp.vdot(y, y) for y in jax.tree.leaves(b)))
    denom = na * nb
    return jnp.where(denom > 0, dot / jnp.where(denom > 0, denom, 1.0), 0.0)

"""Levenberg–Marquardt: damped Gauss–Newton on the joint Jacobian, damping adapted per step.

Sources: Levenberg, *A method for the solution of certain non-linear problems in least
squares*, Q. Appl. Math. 2 (1944); Marquardt, SIAM J. Appl. Math. 11 (1963); the damping
rule of Nielsen, *Damping parameter in Marquardt's method*, IMM-REP-1999-05, as stated in
Madsen, Nielsen & Tingleff, *Methods for non-linear least squares problems* (2004), §3.2.

With the joint per-sample Jacobian ``J = ∂y/∂θ`` of the simulator output and the output
gradient ``g = ∂L/∂y`` of the batch-mean loss, as for Gauss–Newton and HIG
(:mod:`physgrad.methods.hig`),

    d = Jᵀ (J Jᵀ + λ I)⁻¹ g = V Σ (Σ² + λ)⁻¹ Uᵀ g,          θ ← θ − η d,

computed by the same routes (SVD, float64 Gram, structured, block Gram, Lanczos) and the
same truncation: λ → 0 gives physgrad's Gauss–Newton step, λ → ∞ the scaled gradient
``−(η/λ) Jᵀ g``. λ is relative (``λ = μ · σ_max²``, :class:`physgrad.routes.Damped`).

After each step the **gain ratio** compares the actual decrease of the batch loss with the
decrease predicted by the Gauss–Newton model (network and physics linearised, the loss
kept to second order in the outputs):

    ρ = (L(θ) − L(θ + Δ)) / (−(gᵀ u + ½ uᵀ ∇²_y L u)),   u = J Δ,

and μ follows Nielsen's rule: if ρ > 0 the step is taken and μ ← μ · max(⅓, 1 − (2ρ − 1)³),
ν ← 2; otherwise the step is rejected (the parameters stay), μ ← μ · ν, ν ← 2ν. A gain
ratio that is not finite, or a model that predicts no decrease, counts as a rejection.
On mini-batches the loss of the step is measured on the batch that made it (a second
forward pass), as in stochastic LM variants; ``reject=False`` keeps every step and only
adapts μ.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, PyTree

from ..acceptance import AbstractAcceptance
from ..jacobian import require_forward_mode
from ..routes import AbstractRoute, Auto, Damped
from .base import Objective, Stepper, required
from .hig import JacobianPower
from .method import AbstractControl, AbstractOptaxMethod, Method


class DampingState(NamedTuple):
    """:class:`GainRatio`'s state: the relative damping μ and Nielsen's growth factor ν."""

    damping: Array
    growth: Array


def adapt_damping(damping: Array, growth: Array, gain_ratio: Array) -> tuple[Array, Array, Array]:
    """Nielsen's rule: ``(damping, growth, accepted)`` after a step with gain ratio ρ.

    ρ > 0: accepted, μ ← μ · max(⅓, 1 − (2ρ − 1)³), ν ← 2; else (also for a non-finite ρ)
    rejected, μ ← μ · ν, ν ← 2ν. (Madsen, Nielsen & Tingleff 2004, eq. 2.21 and Alg. 3.16.)
    """
    accepted = jnp.isfinite(gain_ratio) & (gain_ratio > 0)
    rho = jnp.where(accepted, gain_ratio, 0.0)
    shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
    damping = jnp.where(accepted, damping * shrink, damping * growth)
    growth = jnp.where(accepted, jnp.asarray(2.0, growth.dtype), 2.0 * growth)
    return damping, growth, accepted


def predicted_decrease(objective: Objective, params: PyTree, batch: PyTree, delta: PyTree) -> Array:
    """``−(gᵀ u + ½ uᵀ ∇²_y L u)`` with ``u = J Δ``: the decrease of the batch-mean loss
    that the Gauss–Newton model predicts for the step ``Δ`` (one JVP through network and
    simulator, then the loss along the line ``y + t u`` to second order in t)."""
    predict, loss = required(objective.predict, "predict"), required(objective.loss, "loss")

    def linearised(sample):
        return jax.jvp(lambda p: predict(p, sample), (params,), (delta,))

    y, u = jax.vmap(linearised)(batch)
    real = jnp.real(y).dtype

    def along(t):  # the batch loss on the linearised outputs y + t u
        return jnp.mean(jax.vmap(loss)(y + t.astype(real) * u, batch))

    def slope(t):
        return jax.jvp(along, (t,), (jnp.ones_like(t),))[1]

    t0 = jnp.zeros((), real)
    first, second = jax.jvp(slope, (t0,), (jnp.ones_like(t0),))
    return -(first + 0.5 * second)


class GainRatio(AbstractAcceptance):
    """Levenberg–Marquardt's acceptance: the gain ratio ρ of the step and Nielsen's rule.

    With the step's updates Δ and its loss measured on the batch that made it,

        ρ = (L(θ) − L(θ + Δ)) / predicted_decrease(Δ),

    accepted ⇔ ρ > 0 (:func:`adapt_damping`; a ρ that is not finite, or a model that
    predicts no decrease, counts as a rejection). The damping is this test's state
    (:class:`DampingState`) because Nielsen's rule adapts it from the verdict, on refused
    steps too; the :class:`Damping` control hands μ to the rule for the next direction
    (:class:`LevenbergMarquardt`; in a :class:`Method` without that control the rule does
    not see μ, and the test only accepts or refuses).
    With ``reject=False`` every step is taken and μ is still adapted.

    Stats: ``damping`` (μ used by the step), ``gain_ratio`` (ρ) and ``accepted`` (1 or 0,
    Nielsen's verdict, also with ``reject=False``).
    """

    damping: float = eqx.field(static=True, default=1e-3)
    reject: bool = eqx.field(static=True, default=True)
    min_damping: float = eqx.field(static=True, default=1e-12)
    max_damping: float = eqx.field(static=True, default=1e12)

    def __check_init__(self):
        if not 0 < self.min_damping <= self.damping <= self.max_damping:
            raise ValueError(f"damping must be positive and within [{self.min_damping:g}, {self.max_damping:g}], "
                             f"got {self.damping}")  # fmt: skip

    def init(self, params):
        dtype = jnp.result_type(*jax.tree.leaves(params)) if jax.tree.leaves(params) else jnp.float32
        real = jnp.real(jnp.zeros((), dtype)).dtype
        return DampingState(jnp.asarray(self.damping, real), jnp.asarray(2.0, real))

    def __call__(self, proposal, state):
        loss = proposal.stats["loss"]
        sample = jax.tree.map(lambda a: a[0], proposal.batch)
        require_forward_mode(required(proposal.objective.predict, "predict"), proposal.params, sample,
                             what="Levenberg–Marquardt's gain ratio (J Δ)", alternative="use gn or hig")  # fmt: skip
        predicted = predicted_decrease(proposal.objective, proposal.params, proposal.batch, proposal.updates)
        actual = loss - proposal.objective.batch_loss(proposal.candidate, proposal.batch)
        gain_ratio = jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1.0), -jnp.inf)
        damping, growth, accepted = adapt_damping(state.damping, state.growth, gain_ratio)
        damping = jnp.clip(damping, self.min_damping, self.max_damping)
        stats = {"damping": state.damping, "gain_ratio": gain_ratio, "accepted": accepted.astype(loss.dtype)}
        return (accepted if self.reject else jnp.asarray(True)), stats, DampingState(damping, growth)


class Damping(AbstractControl):
    """Levenberg–Marquardt's control: the rule's spectral filter damped by the μ of the
    acceptance's state (:class:`DampingState`, kept by :class:`GainRatio`),

        d = V Σ (Σ² + μ σ_max²)⁻¹ Uᵀ g        (:class:`physgrad.routes.Damped`),

    by the rule's route and truncation (:meth:`JacobianPower.filtered`). Keeps no state of
    its own: μ is the acceptance's, adapted from its verdict."""

    def init(self, params):
        return None

    def direct(self, rule, objective, params, batch, state, acceptance):
        if not isinstance(rule, JacobianPower):
            raise ValueError(f"Levenberg–Marquardt's damping needs a JacobianPower rule, got {type(rule).__name__}")
        direction, stats = rule.filtered(objective, params, batch, Damped(acceptance.damping))
        return direction, stats, state


class LevenbergMarquardt(AbstractOptaxMethod):
    """Levenberg–Marquardt on the joint Jacobian with Nielsen's damping rule.

    Use it in a training loop of your own like any engine method::

        lm = LevenbergMarquardt(JacobianPower(-1.0))       # route and truncation of GN
        state = lm.init(params)
        params, state, stats = jax.jit(lm.step, static_argnums=0)(Objective(predict, loss), params, state, batch)

    A final class that fills :class:`AbstractOptaxMethod`'s fields: the rule, the optimizer,
    the acceptance :class:`GainRatio` (Nielsen's rule; μ is its state) and the control
    :class:`Damping` that hands μ to the rule, so ``lm.method``, the same fields as a
    :class:`Method`, steps alike. The state is :class:`physgrad.methods.MethodState`
    ``(optimizer, DampingState(μ, ν))``. ``stats`` holds ``loss`` (before the step), the
    rule's spectrum, ``damping`` (μ used by the step), ``gain_ratio`` (ρ) and ``accepted``
    (1 or 0).

    Fields:
        rule: the Gauss–Newton rule whose route and truncation compute the damped direction.
        optimizer: applies the direction (default ``optax.sgd(1)``: θ ← θ − d).
        damping: the initial μ (relative to σ_max²).
        reject: skip steps whose gain ratio is not positive (LM's acceptance test).
        min_damping, max_damping: bounds on μ, so a long run of good or bad steps cannot
            drive it to 0 or ∞ in floating point.
    """

    rule: JacobianPower = JacobianPower(-1.0)
    optimizer: optax.GradientTransformation = eqx.field(static=True, default=optax.sgd(1.0))
    damping: float = eqx.field(static=True, default=1e-3)
    reject: bool = eqx.field(static=True, default=True)
    min_damping: float = eqx.field(static=True, default=1e-12)
    max_damping: float = eqx.field(static=True, default=1e12)
    extras: tuple[str, ...] = eqx.field(static=True, default=("value",), init=False)
    control: Damping = eqx.field(default=Damping(), init=False)

    def __check_init__(self):
        _ = self.acceptance  # GainRatio checks μ's bounds

    @property
    def acceptance(self) -> GainRatio:
        return GainRatio(self.damping, self.reject, self.min_damping, self.max_damping)

    @property
    def method(self) -> Method:
        """The same fields as a :class:`Method`."""
        return Method(self.rule, self.optimizer, self.acceptance, self.extras, self.control)


def levenberg_marquardt(predict, loss, *, optimizer: optax.GradientTransformation | None = None,
                        damping: float = 1e-3, reject: bool = True, truncation: float = 1e-6,
                        route: AbstractRoute = Auto()) -> Stepper:  # fmt: skip
    """Levenberg–Marquardt bound to your functions and your optax chain.

    ``lm = levenberg_marquardt(predict, loss, optimizer=chain)``; ``state = lm.init(params)``;
    ``params, state, stats = jax.jit(lm.step)(params, state, batch)``. Each step computes the
    damped direction ``d = Jᵀ(J Jᵀ + μ σ_max² I)⁻¹ g`` (the same J, routes and truncation
    as :func:`physgrad.hig`), lets ``optimizer`` turn it into updates, measures the batch loss
    at the candidate and keeps or refuses the step by the gain ratio (:class:`GainRatio`,
    Nielsen's rule, which also adapts μ). LM is a :class:`Stepper` rather than an
    :class:`Estimator` because the acceptance needs the loss after the update: a direction
    alone cannot be accepted or refused. The same pieces apart: ``Method(JacobianPower(-1),
    chain, acceptance=GainRatio(), control=Damping())``; without the control the test
    accepts and refuses without feeding μ back (the direction is then undamped Gauss–Newton).

    Arguments:
        predict, loss: as :func:`physgrad.hig`.
        optimizer: applies the direction (None: ``optax.sgd(1)``, θ ← θ − d).
        damping: the initial μ, relative to σ_max².
        reject: refuse steps whose gain ratio is not positive (False: keep every step and
            only adapt μ).
        truncation, route: as :func:`physgrad.hig`.

    ``stats``: ``loss`` (before the step), the rule's spectrum (``route``, ``rank``,
    ``sigma_max``, ``sigma_min_kept``), ``damping`` (μ used by the step), ``gain_ratio`` (ρ)
    and ``accepted`` (1 or 0).
    """
    optimizer = optax.sgd(1.0) if optimizer is None else optimizer
    method = LevenbergMarquardt(JacobianPower(-1.0, truncation, route), optimizer, damping=damping, reject=reject)  # pyright: ignore[reportCallIssue]  (acceptance is a property)
    return Stepper(method, Objective(predict, loss))

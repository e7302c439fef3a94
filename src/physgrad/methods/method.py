"""The methods that apply a rule by optax, implemented once (:class:`AbstractOptaxMethod`),
and the pairing users build (:class:`Method`).

A step (``θ`` the trainable arrays, ``d`` the rule's direction, ``Δ`` the optimizer's updates)::

    d, stats      = rule(objective, θ, batch)                    # or control.direct(rule, …, state)
    Δ, opt_state  = optimizer.update(d, opt_state, θ, **extras)
    θ'            = θ + Δ,   kept if acceptance(θ, d, Δ, θ + Δ) accepts, else θ (and opt_state)

Levenberg–Marquardt, unrolled training and KHIG with running factors are final classes of
:class:`AbstractOptaxMethod` that fill its fields (optimistix's ``AbstractGaussNewton`` and
its final ``LevenbergMarquardt`` are the model): what couples one step to the next beyond
the optimizer's state is a control (:class:`AbstractControl`) that hands the rule a value
from the state.
"""

# No `from __future__ import annotations` here: Equinox reads `AbstractVar[...]` fields from
# evaluated annotations only (stringified abstract annotations are refused or, spelled
# `eqx.AbstractVar[...]`, taken for plain fields).

import abc
import dataclasses
from typing import Any, NamedTuple

import equinox as eqx
import optax
from equinox import AbstractVar
from jaxtyping import PyTree

from ..acceptance import AbstractAcceptance, Proposal, keep_where
from .base import AbstractMethod, AbstractRule, Objective, Stats, trainable, with_extra_args


class MethodState(NamedTuple):
    """An :class:`AbstractOptaxMethod`'s state when it has an acceptance or a stateful
    control: the optimizer's, the acceptance's (None without one) and the control's (None
    when it keeps none, and then absent from the leaves: a state with an acceptance alone
    flattens as the pair it was)."""

    optimizer: PyTree
    acceptance: Any
    control: Any = None


class AbstractControl(eqx.Module):
    """What a method's state hands its rule each step besides the parameters, and how the
    rule takes it: ``direct(rule, objective, params, batch, state, acceptance) ->
    (direction, stats, state)``.

    The coupling between a step and the next that is not the optimizer's: Levenberg–
    Marquardt's damping μ, which its acceptance (:class:`physgrad.methods.GainRatio`) adapts
    and the rule's spectral filter reads (:class:`physgrad.methods.lm.Damping`), and KHIG's
    running Kronecker factors (:class:`physgrad.methods.averaged_kronecker.RunningFactors`).
    ``state`` is the control's own (``init``), ``acceptance`` the acceptance's before the
    step. A control knows the rule it drives (its ``direct`` calls that rule's own entry
    with the control value), so rules without one keep the plain ``rule(objective, params,
    batch)``.
    """

    @abc.abstractmethod
    def init(self, params: PyTree) -> Any:
        """The control's state before the first step (None: it keeps none)."""

    @abc.abstractmethod
    def direct(
        self, rule: AbstractRule, objective: Objective, params: PyTree, batch: PyTree, state: Any, acceptance: Any
    ) -> tuple[PyTree, Stats, Any]: ...


_EXTRAS = ("value", "grad", "value_fn", "obj_fn")


class AbstractOptaxMethod(AbstractMethod):
    """A rule applied by an optax transformation: ``θ ← θ + optimizer(d)``, d = rule(θ),
    the step taken if ``acceptance`` accepts it; implemented once for every such method
    (:class:`Method`, :class:`physgrad.methods.LevenbergMarquardt`,
    :class:`physgrad.methods.AveragedKronecker`, :class:`physgrad.methods.Unrolled`), whose
    final classes only fill these fields (optimistix's ``AbstractGaussNewton`` and its
    ``LevenbergMarquardt`` are the model):

    - ``rule``: the direction (:class:`AbstractRule`).
    - ``optimizer``: the optax transformation that turns it into updates.
    - ``acceptance``: a :class:`physgrad.acceptance.AbstractAcceptance` that may refuse a
      step (parameters and optimizer state then stay as they were) and adds its
      statistics; None takes every step.
    - ``extras``: the keyword extras the optimizer's update receives (:class:`Method`).
    - ``control``: an :class:`AbstractControl` that hands the rule a value from the state
      (Levenberg–Marquardt's damping, KHIG's running factors); None: ``rule(objective,
      params, batch)``.

    The state is the optimizer's alone without acceptance and control, else
    :class:`MethodState`. ``params`` may be a whole Equinox module: the optimizer's state
    and updates cover its inexact-array leaves (:func:`trainable`); the other leaves come
    back unchanged. The optimizer's state is a few copies of the parameters, small next to
    what the rules that estimate memory hold (Jacobians): the rule's footprint is the
    method's.
    """

    rule: AbstractVar[AbstractRule]
    optimizer: AbstractVar[optax.GradientTransformation]
    acceptance: AbstractVar[AbstractAcceptance | None]
    extras: AbstractVar[tuple[str, ...]]
    control: AbstractVar[AbstractControl | None]

    def __check_init__(self):
        unknown = set(self.extras) - set(_EXTRAS)
        if unknown:
            raise ValueError(f"unknown optimizer extras {sorted(unknown)}; valid choices: {', '.join(sorted(_EXTRAS))}")

    def init(self, params):
        arrays = trainable(params)[0]
        optimizer = self.optimizer.init(arrays)
        acceptance = None if self.acceptance is None else self.acceptance.init(arrays)
        control = None if self.control is None else self.control.init(arrays)
        if self.acceptance is None and self.control is None:
            return optimizer
        return MethodState(optimizer, acceptance, control)

    def check(self, objective):
        self.rule.check(objective)

    def check_batch_size(self, batch_size):
        self.rule.check_batch_size(batch_size)

    def footprint(self, objective, params, batch, devices=1):
        arrays, static = trainable(params)
        return self.rule.footprint(objective.bind_static(static), arrays, batch, devices)

    def footprint_note(self, objective, params, batch):
        arrays, static = trainable(params)
        return self.rule.footprint_note(objective.bind_static(static), arrays, batch)

    def lighter(self, batch_size):
        return [dataclasses.replace(self, rule=rule) for rule in self.rule.lighter(batch_size)]

    def statistics(self, stats: Stats, state: Any) -> Stats:
        """The step's statistics as reported, from those of the rule and the acceptance and
        the state after the step; as they are by default."""
        return stats

    def step(self, objective, params, state, batch):
        arrays, static = trainable(params)
        objective = objective.bind_static(static)
        if self.acceptance is None and self.control is None:
            opt_state, accept_state, control_state = state, None, None
        else:
            opt_state, accept_state, control_state = state
        if self.control is None:
            direction, stats = self.rule(objective, arrays, batch)
        else:
            direction, stats, control_state = self.control.direct(
                self.rule, objective, arrays, batch, control_state, accept_state
            )

        def batch_loss(p):
            return objective.batch_loss(p, batch)

        available = {"value": stats["loss"], "grad": direction, "value_fn": batch_loss, "obj_fn": batch_loss}
        extras = {name: available[name] for name in self.extras}
        updates, new_opt_state = with_extra_args(self.optimizer).update(direction, opt_state, arrays, **extras)
        candidate = optax.apply_updates(arrays, updates)
        if self.acceptance is None:
            arrays, opt_state = candidate, new_opt_state
        else:
            proposal = Proposal(objective, arrays, batch, direction, updates, candidate, stats)
            accepted, verdict, accept_state = self.acceptance(proposal, accept_state)
            arrays, opt_state = keep_where(accepted, (candidate, new_opt_state), (arrays, opt_state))
            stats = {**stats, **verdict}
        if self.acceptance is None and self.control is None:
            state = opt_state
        else:
            state = MethodState(opt_state, accept_state, control_state)
        return eqx.combine(arrays, static), state, self.statistics(stats, state)


class Method(AbstractOptaxMethod):
    """A rule applied by an optax transformation: ``θ ← θ + optimizer(d)``, d = rule(θ),
    the step taken if ``acceptance`` accepts it (:class:`AbstractOptaxMethod`).

    Fields:
        rule: the direction (:class:`AbstractRule`).
        optimizer: the optax transformation that turns it into updates.
        acceptance: a :class:`physgrad.acceptance.AbstractAcceptance` that may refuse a
            step (parameters and optimizer state then stay as they were) and adds its
            statistics; None (the default) takes every step. The state is then
            :class:`MethodState` ``(optimizer, acceptance)``, else the optimizer's alone.
        extras: the keyword extras the optimizer's update receives, from ``value`` (the
            batch loss), ``grad`` (the direction), ``value_fn`` and ``obj_fn`` (the batch
            loss as a function of the parameters on this batch) — what optax's
            line-search L-BFGS (``optax.lbfgs``: value, grad, value_fn) and Sophia's
            Hessian estimate (``optax.contrib.sophia``: obj_fn) ask for. Only the named ones
            are passed because some optax transformations refuse extras they do not
            consume; the default ``("value",)`` is ignored by chains that do not use it.
        control: an :class:`AbstractControl` handing the rule a value from the state
            (None, the default: the rule alone). ``Method(JacobianPower(-1), chain,
            GainRatio(), control=Damping())`` is Levenberg–Marquardt; without the control
            the gain-ratio test accepts and refuses an undamped Gauss–Newton step.
    """

    rule: AbstractRule
    optimizer: optax.GradientTransformation = eqx.field(static=True)
    acceptance: AbstractAcceptance | None = None
    extras: tuple[str, ...] = eqx.field(static=True, default=("value",))
    control: AbstractControl | None = None


__all__ = ["AbstractControl", "AbstractOptaxMethod", "Method", "MethodState"]

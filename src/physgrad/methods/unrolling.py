"""Training modalities of neural time-steppers: one-step, no-gradient unrolled, fully differentiable.

List, Chen, Bali & Thuerey, *Differentiability in unrolled training of neural physics
simulators on transient dynamics*, CMAME 2025 (§2). With the rollout u⁰ = ũ⁰,
uᵏ = S_θ(uᵏ⁻¹) and L = (1/m) Σ_k MSE(uᵏ, ũᵏ):

- ONE: every step starts from the reference frame ũᵏ⁻¹ (teacher forcing), so the
  gradient is (1/m) Σ_k ∂ℓ_k/∂θ at ground-truth inputs. Budget parity with the unrolled
  modalities (the authors' KS code trains ONE with batch B·m and epochs × m): a batch of B
  windows gives B·m one-step targets per update and one epoch over the windows visits
  every pair m times, so updates and targets match NOG/WIG at equal batch size and epochs.
- NOG: the m-step rollout on the model's own predictions, with the gradient stopped on
  each state after its loss (policy ``S``): Σ_k ∂ℓ_k/∂uᵏ · ∂S_θ/∂θ(uᵏ⁻¹). The solver's
  input is stopped statically, so it is never differentiated.
- WIG: the full BPTT gradient through network and solver (policy ``R``), with
  ``truncate=k`` (cut every k steps) and ``warmup=W`` (the first W steps run without
  gradient and without loss: the pushforward trick). Refuses a non-differentiable solver.

The direction is :class:`UnrolledGradient` (and :func:`physgrad.unrolled` for a user's own
rollout system). The engine's :class:`Unrolled` applies it with the paper's stabilisers:
a learning-rate schedule (``optax.linear_schedule`` warm-up times
``optax.exponential_decay``: lr ← decay·lr every ``decay_every`` steps) and global-norm
clipping in Adam's optax chain, and update skipping by acceptance tests
(:mod:`physgrad.acceptance`) — :class:`~physgrad.acceptance.FiniteGradient` on a
non-finite gradient (``optax.apply_if_finite``'s test), :class:`~physgrad.acceptance.NormBound`
on a norm above a running bound (the rule of :func:`physgrad.transforms.norm_guard`), and
:class:`~physgrad.acceptance.SolverSuccess` when the solver reports a failure; a skipped
step leaves parameters and optimizer state as they were. Skips are counted in the step
statistics ``skipped``, ``skip_nan``, ``skip_norm`` and ``skip_solver``. A curriculum
(stages of increasing m, each ``stage_epochs`` long with its own learning rate and a fresh
Adam) is declared by ``stages()``. An optional :class:`Plateau` multiplies the learning rate
by a factor whenever the epoch-mean training loss stops improving (PyTorch's
``ReduceLROnPlateau``, by ``optax.contrib.reduce_on_plateau``).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import optax
import optax.contrib

from ..acceptance import All, FiniteGradient, NormBound, SolverSuccess
from ..rollout import GradientFlow, R, S, value_and_grad
from .base import UNROLLED, AbstractRule, Estimator, Objective, Part, required
from .method import AbstractOptaxMethod, Method


class UnrolledGradient(AbstractRule):
    """The gradient of the unrolled time-stepper loss under a gradient-flow policy.

    Statistics: ``loss``, ``grad_norm`` (global L2 norm) and ``solver_ok`` (no solver
    failure flagged in the rollout's final state)."""

    policy: GradientFlow = R()
    teacher_forcing: bool = eqx.field(static=True, default=False)
    m: int = eqx.field(static=True, default=0)  # 0: the problem's window length
    checkpoint: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.m < 0:
            raise ValueError("unroll lengths (m, curriculum) must be positive")

    def system(self, objective):
        return objective.unrolled(self.m or None, self.teacher_forcing)

    @property
    def part(self) -> Part:  # pyright: ignore[reportIncompatibleVariableOverride]
        """The unrolled windows of this rule's m (their system is built on every check, which
        refuses an m beyond the problem's windows), differentiated through the solver unless
        the rule forces the teacher's inputs or its policy stops the gradient there."""
        return UNROLLED._replace(
            differentiable=not self.teacher_forcing and not self.policy.stop_physics,
            solver=lambda objective: self.system(objective).differentiable_physics,
        )

    def __call__(self, objective, params, batch):
        system = self.system(objective)
        s0 = system.initial_state(batch)
        policy = S() if self.teacher_forcing else self.policy  # inputs are data: nothing to stop
        (loss, final), grads = value_and_grad(system, params, s0, policy, checkpoint=self.checkpoint, has_aux=True)
        ok = jnp.all(final["ok"]) if isinstance(final, dict) and "ok" in final else jnp.asarray(True)
        return grads, {"loss": loss, "grad_norm": optax.tree.norm(grads), "solver_ok": ok}


def unrolled(system, *, policy: GradientFlow = S(), checkpoint: bool = False) -> Estimator:
    """The unrolled-training gradient of a time-stepper rollout: ``(params, batch) -> (g, stats)``.

    ``policy=S()`` is NOG, ``R()`` WIG (with ``truncate``/``warmup`` cuts); ONE is NOG on a
    teacher-forced system (every step reads the reference frame). ``system`` is a
    :class:`physgrad.rollout.System`; its final state may carry an ``"ok"`` flag per sample
    (solver failures), reported as ``stats["solver_ok"]``.
    """
    return Estimator(
        UnrolledGradient(policy, False, 0, checkpoint), Objective(unrolled=lambda m=None, tf=False: system)
    )


def schedule(lr: float, warmup: int = 0, decay: float = 1.0, every: int = 0) -> optax.Schedule:
    """``lr · min(1, (t+1)/warmup) · decay^⌊t/every⌋`` from optax's schedules (t = updates
    applied so far): a linear warm-up over the first ``warmup`` updates (KOLM: 64·m) times
    a staircase exponential decay (KS: 0.9 every 2000)."""
    decayed = (
        optax.exponential_decay(lr, every, decay, staircase=True)
        if every and decay != 1.0
        else optax.constant_schedule(lr)
    )
    if not warmup:
        return decayed
    ramp = optax.linear_schedule(1.0 / warmup, 1.0, max(warmup - 1, 1))
    return lambda t: ramp(t) * decayed(t)


class Plateau(eqx.Module):
    """Reduce the learning rate on a plateau of the training loss: PyTorch's
    ``torch.optim.lr_scheduler.ReduceLROnPlateau`` (mode ``min``, relative threshold) on the
    mean batch loss of every ``every`` applied updates (one epoch when ``every`` is the
    epoch's number of updates), by ``optax.contrib.reduce_on_plateau`` placed after Adam
    (Adam's update is linear in its learning rate, so scaling it scales the rate).

    After decision e, with L̄_e the mean of the batch losses (``stats["loss"]``, before each
    update) of its ``every`` updates, best the lowest L̄ so far, bad the count of decisions
    without improvement and s the scale (1 at the start)::

        improved = L̄_e < (1 − threshold) · best;   best ← L̄_e if improved
        bad ← 0 if improved else bad + 1
        if cooldown_left > 0:  cooldown_left ← cooldown_left − 1,  bad ← 0
        elif bad > patience:   s ← max(factor · s, min_scale),  bad ← 0,  cooldown_left ← cooldown

        lr_t = s · schedule(t)   (s constant between decisions)

    A decision takes effect from the update that completes its epoch (optax's order), one
    update before PyTorch's ``scheduler.step()`` after the epoch would.

    ``patience`` is PyTorch's: the rate falls at the (patience + 1)-th decision in a row
    without improvement; optax's ``patience`` counts that decision itself, so it gets
    ``patience + 1`` (the equivalence is tested against a hand-written copy of PyTorch's
    ``step``). PyTorch's ``eps`` (a fall smaller than 1e-8 in the rate is skipped) has no
    optax counterpart; ``min_scale`` bounds the scale instead. A skipped update (an
    acceptance test failed) leaves the optimizer state, and so the accumulation, as it was.

    The defaults are PyTorch's (factor 0.1, patience 10, threshold 1e-4, cooldown 0): the
    authors' re-run of the KS experiment (TUM blog, 2024) trained "with a plateau scheduler"
    and names no parameters; their code is PyTorch, whose scheduler these defaults are when
    none is given, and the monitored quantity is the training loss, the only loss their KS
    training loop computes (it has no validation split). That choice is ours, not the
    authors'. ``every`` has no default: the method does not know the epoch's length (KS at
    batch 16: 2,808 updates, ONE's as NOG's and WIG's by the budget parity above).

    Sources: PyTorch, ``torch.optim.lr_scheduler.ReduceLROnPlateau`` (its ``step`` and
    defaults); optax, ``optax.contrib.reduce_on_plateau`` (``accumulation_size``: the mean
    over ``every`` values before each decision).
    """

    every: int = eqx.field(static=True)
    factor: float = eqx.field(static=True, default=0.1)
    patience: int = eqx.field(static=True, default=10)
    cooldown: int = eqx.field(static=True, default=0)
    threshold: float = eqx.field(static=True, default=1e-4)
    min_scale: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        if not 0.0 < self.factor < 1.0:
            raise ValueError(f"plateau_factor must lie in (0, 1), got {self.factor}")
        if self.every < 1:
            raise ValueError(
                f"plateau_every (updates per plateau decision, e.g. one epoch) must be >= 1, got {self.every}"
            )
        if self.patience < 0 or self.cooldown < 0:
            raise ValueError("plateau_patience and plateau_cooldown must be >= 0")
        if not 0.0 < self.threshold <= 1.0 or self.min_scale < 0.0:
            raise ValueError("the plateau threshold must lie in (0, 1] and min_scale be >= 0")

    def transformation(self) -> optax.GradientTransformationExtraArgs:
        """The optax transformation (reads the batch loss as ``value=``)."""
        return optax.contrib.reduce_on_plateau(
            factor=self.factor,
            patience=self.patience + 1,  # PyTorch's patience: see the class docstring
            rtol=self.threshold,
            atol=0.0,
            cooldown=self.cooldown,
            accumulation_size=self.every,
            min_scale=self.min_scale,
        )


class Unrolled(AbstractOptaxMethod):
    """The unrolled gradient applied by Adam with the stabilisers of the module docstring.

    A final class that fills :class:`physgrad.methods.AbstractOptaxMethod`'s fields
    from its settings: the schedule and clipping in ``optimizer``, the skipping in
    ``acceptance``; plus the curriculum's stages. The state is
    :class:`physgrad.methods.MethodState` (the running norm bound is its acceptance
    state's ``bound``).

    Fields: ``rule``; ``lr``, ``lr_warmup``, ``decay``, ``decay_every`` (:func:`schedule`);
    ``clip`` (global norm, 0: off); ``skip_nan``, ``norm_guard``, ``skip_solver_failure``
    (which skips are enforced: an unenforced finite or solver test still reports, a norm
    bound that is off reports 0); ``curriculum``, ``stage_epochs``, ``stage_lr``;
    ``plateau`` (a :class:`Plateau`, None: off, the default; each curriculum stage starts
    it afresh with its Adam). With a plateau the statistic ``lr_scale`` is its scale s.
    """

    rule: UnrolledGradient
    lr: float = eqx.field(static=True, default=1e-3)
    lr_warmup: int = eqx.field(static=True, default=0)
    decay: float = eqx.field(static=True, default=1.0)
    decay_every: int = eqx.field(static=True, default=0)
    clip: float = eqx.field(static=True, default=0.0)
    skip_nan: bool = eqx.field(static=True, default=True)
    norm_guard: bool = eqx.field(static=True, default=False)
    skip_solver_failure: bool = eqx.field(static=True, default=True)
    curriculum: tuple[int, ...] = eqx.field(static=True, default=())
    stage_epochs: float = eqx.field(static=True, default=1.0)
    stage_lr: tuple[float, ...] = eqx.field(static=True, default=())
    plateau: Plateau | None = eqx.field(static=True, default=None)
    extras: tuple[str, ...] = eqx.field(static=True, default=("value",), init=False)
    control: None = eqx.field(default=None, init=False)

    def __check_init__(self):
        if any(m < 1 for m in self.curriculum):
            raise ValueError("unroll lengths (m, curriculum) must be positive")
        if self.stage_lr and len(self.stage_lr) != len(self.curriculum):
            raise ValueError(f"stage_lr needs one learning rate per curriculum stage ({len(self.curriculum)})")
        if self.curriculum and self.stage_epochs <= 0:
            raise ValueError("stage_epochs must be positive")
        if self.lr <= 0 or any(lr <= 0 for lr in self.stage_lr):
            raise ValueError("learning rates must be positive")

    @property
    def m(self) -> int:
        return self.rule.m

    @property
    def policy(self) -> GradientFlow:
        return self.rule.policy

    @property
    def teacher_forcing(self) -> bool:
        return self.rule.teacher_forcing

    def stages(self):
        """The curriculum as (method, epochs) stages; the last runs until the budget ends."""
        if not self.curriculum:
            return [(self, None)]
        lrs = self.stage_lr or (self.lr,) * len(self.curriculum)
        out = []
        for i, (m, lr) in enumerate(zip(self.curriculum, lrs)):
            stage = dataclasses.replace(
                self, rule=dataclasses.replace(self.rule, m=m), lr=lr, curriculum=(), stage_lr=()
            )
            out.append((stage, None if i == len(self.curriculum) - 1 else self.stage_epochs))
        return out

    def stage_label(self):
        return f"m={self.rule.m}"

    @property
    def optimizer(self) -> optax.GradientTransformation:
        """Adam on the schedule, after global-norm clipping when ``clip`` > 0, its updates
        scaled by the :class:`Plateau` when there is one (the chain's last state)."""
        chain = [optax.clip_by_global_norm(self.clip)] if self.clip > 0 else []
        plateau = [self.plateau.transformation()] if self.plateau is not None else []
        adam = optax.adam(schedule(self.lr, self.lr_warmup, self.decay, self.decay_every))
        return optax.chain(*chain, adam, *plateau)

    @property
    def acceptance(self) -> All:
        """The skips as acceptance tests; a finite-gradient or solver test that is off is
        still judged, so its statistic says why a step skipped for another reason failed."""
        norm = (NormBound(),) if self.norm_guard else ()
        return All(FiniteGradient(enforce=self.skip_nan), *norm, SolverSuccess(enforce=self.skip_solver_failure))

    @property
    def method(self) -> Method:
        """The same rule, optimizer and acceptance as a :class:`Method` (whose step reports
        the statistics as they come, without :meth:`statistics`)."""
        return Method(self.rule, self.optimizer, self.acceptance)

    def check(self, objective):
        self.rule.check(objective)
        for m in self.curriculum:
            required(objective.unrolled, "unrolled")(m, self.rule.teacher_forcing)  # raises if m exceeds the windows

    def statistics(self, stats, state):
        stats = dict(stats)
        del stats["solver_ok"]  # SolverSuccess's input, reported as skip_solver
        if not self.norm_guard:  # the same statistics with the bound off (the recorder sorts them)
            stats["skip_norm"] = jnp.zeros((), jnp.float32)
        if self.plateau is not None:
            stats["lr_scale"] = state.optimizer[-1].scale
        return stats

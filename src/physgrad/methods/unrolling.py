"""Training modalities of neural time-steppers: one-step, no-gradient unrolled, fully differentiable.

List, Chen, Bali & Thuerey, CMAME 2025 (shared/papers/unrolling.md §1.2, §5). With the
rollout u⁰ = ũ⁰, uᵏ = S_θ(uᵏ⁻¹) and L = (1/m) Σ_k MSE(uᵏ, ũᵏ):

- ``one`` (ONE): every step starts from the reference frame ũᵏ⁻¹ (teacher forcing), so the
  gradient is (1/m) Σ_k ∂ℓ_k/∂θ at ground-truth inputs. Budget parity with the unrolled
  modalities (the KS code trains ONE with batch B·m and epochs × m): a batch of B windows
  gives B·m one-step targets per update and one epoch over the windows visits every pair
  m times, so updates and targets match ``nog``/``wig`` at the same batch size and epochs.
- ``nog`` (NOG): the m-step rollout on the model's own predictions, with the gradient
  stopped on each state after its loss (policy ``S``): Σ_k ∂ℓ_k/∂uᵏ · ∂S_θ/∂θ(uᵏ⁻¹). The
  solver's input is stopped statically, so it is never differentiated.
- ``wig`` (WIG): the full BPTT gradient through network and solver (policy ``R``), with
  ``truncate=k`` (cut every k steps) and ``warmup=W`` (the first W steps run without
  gradient and without loss: the pushforward trick). Refuses a non-differentiable solver.

Stabilisers (§1.4B, §5.4), all options of every modality:

- ``curriculum="1,2,4"``: stages of increasing unroll length, each ``stage_epochs`` long
  (the last runs until the budget is spent), with ``stage_lr`` per stage and a fresh Adam;
- ``lr_warmup``: linear learning-rate warm-up over the first steps of each stage (KOLM:
  64·m); ``decay``/``decay_every``: lr ← decay·lr every ``decay_every`` steps (KS: 0.9
  every 2000);
- update skipping, counted in the step statistics ``skipped``, ``skip_nan``, ``skip_norm``
  and ``skip_solver``: on a non-finite gradient; on a gradient norm above a running bound
  (``norm_guard``: c ← 0.9c + 10‖g‖ after each accepted update, ≈ 100× the mean norm;
  the first update sets c = 100‖g‖); and when the solver reports a failure;
- ``clip``: global-norm clipping (0 = off).

Logged per step: ``loss``, ``grad_norm`` and the skip counters.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

from ..rollout import GradientFlow, R, S, value_and_grad
from .base import AbstractMethod


def parse_list(text: str, kind, name: str) -> tuple:
    """A comma-separated setting (``"1,2,4"``) as a tuple; a one-line error otherwise."""
    try:
        return tuple(kind(t) for t in str(text).split(",") if t.strip())
    except ValueError:
        raise ValueError(f"{name} must be a comma-separated list of numbers, got {text!r}") from None


class Unrolled(AbstractMethod):
    """A gradient of the unrolled time-stepper loss under a gradient-flow policy, applied by
    Adam with the stabilisers of the module docstring."""

    policy: GradientFlow
    teacher_forcing: bool = eqx.field(static=True, default=False)
    m: int = eqx.field(static=True, default=0)  # 0: the problem's window length
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
    checkpoint: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.m < 0 or any(m < 1 for m in self.curriculum):
            raise ValueError("unroll lengths (m, curriculum) must be positive")
        if self.stage_lr and len(self.stage_lr) != len(self.curriculum):
            raise ValueError(f"stage_lr needs one learning rate per curriculum stage ({len(self.curriculum)})")
        if self.curriculum and self.stage_epochs <= 0:
            raise ValueError("stage_epochs must be positive")
        if self.lr <= 0 or any(lr <= 0 for lr in self.stage_lr):
            raise ValueError("learning rates must be positive")

    def stages(self) -> list[tuple[Unrolled, float | None]]:
        """The curriculum as (method, epochs) stages; the last runs until the budget ends."""
        if not self.curriculum:
            return [(self, None)]
        lrs = self.stage_lr or (self.lr,) * len(self.curriculum)
        out = []
        for i, (m, lr) in enumerate(zip(self.curriculum, lrs)):
            stage = dataclasses.replace(self, m=m, lr=lr, curriculum=(), stage_lr=())
            out.append((stage, None if i == len(self.curriculum) - 1 else self.stage_epochs))
        return out

    @property
    def optimizer(self) -> optax.GradientTransformation:
        lr, warmup, decay, every = self.lr, self.lr_warmup, self.decay, self.decay_every

        def schedule(t):
            scale = jnp.minimum(1.0, (t + 1) / warmup) if warmup else 1.0
            if every and decay != 1.0:
                scale = scale * decay ** jnp.floor(t / every)
            return lr * scale

        chain = [optax.clip_by_global_norm(self.clip)] if self.clip > 0 else []
        return optax.chain(*chain, optax.adam(schedule))

    def init(self, params):
        return self.optimizer.init(params), jnp.zeros((), jnp.float32)

    def check(self, objective):
        if objective.unrolled is None:
            raise ValueError("this method trains a neural time-stepper; use a time-stepper problem (ks, kolmogorov, advection_1d)")
        system = objective.unrolled(self.m or None, self.teacher_forcing)
        for m in self.curriculum:
            objective.unrolled(m, self.teacher_forcing)  # raises if m exceeds the windows
        if not system.differentiable_physics and not self.teacher_forcing and not self.policy.stop_physics:
            raise ValueError(
                "this method differentiates through the solver, but the problem's solver is not "
                "differentiable; train with nog or one"
            )

    def step(self, objective, params, state, batch):
        opt_state, cutoff = state
        system = objective.unrolled(self.m or None, self.teacher_forcing)
        s0 = system.initial_state(batch)
        policy = S() if self.teacher_forcing else self.policy  # inputs are data: nothing to stop
        (loss, final), grads = value_and_grad(system, params, s0, policy, checkpoint=self.checkpoint, has_aux=True)
        norm = optax.tree.norm(grads)
        finite = jnp.isfinite(norm)
        solver_ok = jnp.all(final["ok"])
        within = (cutoff == 0) | (norm <= cutoff)
        accept = jnp.asarray(True)
        if self.skip_nan:
            accept = accept & finite
        if self.norm_guard:
            accept = accept & within
        if self.skip_solver_failure:
            accept = accept & solver_ok
        updates, new_opt = self.optimizer.update(grads, opt_state, params)
        new_params = optax.apply_updates(params, updates)
        keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(accept, a, b), new, old)  # noqa: E731
        new_cutoff = jnp.where(cutoff == 0, 100.0 * norm, 0.9 * cutoff + 10.0 * norm).astype(cutoff.dtype)
        cutoff = jnp.where(accept & self.norm_guard, new_cutoff, cutoff)
        skipped = ~accept
        stats = {
            "loss": loss,
            "grad_norm": norm,
            "skipped": skipped.astype(jnp.float32),
            "skip_nan": (skipped & ~finite).astype(jnp.float32),
            "skip_norm": (skipped & finite & ~within & self.norm_guard).astype(jnp.float32),
            "skip_solver": (skipped & ~solver_ok).astype(jnp.float32),
        }
        return keep(new_params, params), (keep(new_opt, opt_state), cutoff), stats


def _unrolled(policy, teacher_forcing, *, m, lr, lr_warmup, decay, decay_every, clip, skip_nan, norm_guard,
              skip_solver_failure, curriculum, stage_epochs, stage_lr, checkpoint):  # fmt: skip
    return Unrolled(
        policy, teacher_forcing, m, lr, lr_warmup, decay, decay_every, clip, skip_nan, norm_guard,
        skip_solver_failure, parse_list(curriculum, int, "curriculum"), stage_epochs,
        parse_list(stage_lr, float, "stage_lr"), checkpoint,
    )  # fmt: skip


def one(*, lr: float = 1e-3, lr_warmup: int = 0, decay: float = 1.0, decay_every: int = 0, clip: float = 0.0,
        skip_nan: bool = True, norm_guard: bool = False, skip_solver_failure: bool = True, m: int = 0):  # fmt: skip
    """One-step training (ONE): every step from the reference frame; B·m targets per update."""
    return _unrolled(S(), True, m=m, lr=lr, lr_warmup=lr_warmup, decay=decay, decay_every=decay_every, clip=clip,
                     skip_nan=skip_nan, norm_guard=norm_guard, skip_solver_failure=skip_solver_failure,
                     curriculum="", stage_epochs=1.0, stage_lr="", checkpoint=False)  # fmt: skip


def nog(*, lr: float = 1e-3, lr_warmup: int = 0, decay: float = 1.0, decay_every: int = 0, clip: float = 0.0,
        skip_nan: bool = True, norm_guard: bool = False, skip_solver_failure: bool = True, m: int = 0,
        curriculum: str = "", stage_epochs: float = 1.0, stage_lr: str = "", checkpoint: bool = False):  # fmt: skip
    """No-gradient unrolling (NOG): m-step rollout, stop-gradient on each state after its loss."""
    return _unrolled(S(), False, m=m, lr=lr, lr_warmup=lr_warmup, decay=decay, decay_every=decay_every, clip=clip,
                     skip_nan=skip_nan, norm_guard=norm_guard, skip_solver_failure=skip_solver_failure,
                     curriculum=curriculum, stage_epochs=stage_epochs, stage_lr=stage_lr, checkpoint=checkpoint)  # fmt: skip


def wig(*, lr: float = 1e-3, lr_warmup: int = 0, decay: float = 1.0, decay_every: int = 0, clip: float = 0.0,
        skip_nan: bool = True, norm_guard: bool = False, skip_solver_failure: bool = True, m: int = 0,
        truncate: int = 0, warmup: int = 0, curriculum: str = "", stage_epochs: float = 1.0, stage_lr: str = "",
        checkpoint: bool = False):  # fmt: skip
    """Fully differentiable unrolling (WIG): BPTT through network and solver; truncate/warmup cuts."""
    return _unrolled(R(truncate=truncate, warmup=warmup), False, m=m, lr=lr, lr_warmup=lr_warmup, decay=decay,
                     decay_every=decay_every, clip=clip, skip_nan=skip_nan, norm_guard=norm_guard,
                     skip_solver_failure=skip_solver_failure, curriculum=curriculum, stage_epochs=stage_epochs,
                     stage_lr=stage_lr, checkpoint=checkpoint)  # fmt: skip

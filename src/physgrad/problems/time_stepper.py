"""Neural time-stepper problems: learn u^{k+1} = S_θ(u^k) from reference trajectories.

List, Chen, Bali & Thuerey, CMAME 2025. A training
sample is a window of m+1 reference frames ũ⁰…ũᵐ with its conditioning value; the stepper
S_θ (a composition object of :mod:`physgrad.problems.sim.steppers`: a prediction, or a correction of a
coarse solver) is rolled out from ũ⁰ and scored by

    L = (1/m) Σ_{k=1..m} ℓ_k,      ℓ_k = MSE(uᵏ, ũᵏ)

(the KS code's ``MSELoss`` over the stacked outputs). The training modalities differ only
in the gradient-flow policy of the shared rollout engine (:mod:`physgrad.methods.unrolling`):
``one`` teacher-forces every step (inputs are reference frames), ``nog`` stops the gradient
on each state after its loss, ``wig`` differentiates through network and solver.

Data are generated from ``data_seed`` by the problem's reference solver and cached on disk
(``$PHYSGRAD_CACHE``, default ``~/.cache/physgrad``), keyed by every setting that changes
them and by the exponax version; no downloads. Splits: ``train`` (all overlapping windows of
m+1 frames, materialised), ``val`` (short trajectories for schedule decisions such as PRDP)
and ``test`` (trajectories of ``long_horizon`` frames from held-out conditions or seeds).

Batches: shuffled by default (``shuffle=true``, as the authors' code): every epoch a fresh
permutation of the windows, drawn from the run's seed; ``--set shuffle=false`` takes them in
stored order (consecutive windows of one trajectory per batch; physgrad's default before
issue 32). KS keeps each batch within one domain size (its ``batch_groups``).

Open-loop contract (so ``adam`` & co. run too, as plain BPTT): ``network_output`` rolls the
stepper out over the whole sample, ``simulate`` is the identity, ``loss`` is L on the first
m steps. Metrics on trajectories at least ``eval_horizon`` long (§1.5):

- ``rel_error``: mean over t ≤ eval_horizon and x of (u − ũ)² / max_{t,x} ũ², clipped at 30
  (the KS code's ``rellinf``);
- ``nrmse``: the same horizon's mean of ‖u − ũ‖ / ‖ũ‖ per frame;
- ``corr_time``: steps until the correlation with the reference first drops below 0.2,
  over the whole test trajectory (the decorrelation time; the horizon if it never does).
  The KS code also requires it to stay below 0.2 for 5 steps; we count the first crossing;
- ``diverged``: 1 if the rollout became non-finite or exceeded 100× the reference's
  maximum within the trajectory.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import loops
from ..errors import NotRefinable, warn_deprecated
from ..rollout import System
from .base import AbstractProblem
from .sim.cache import cached_arrays
from .sim.steppers import (
    AbstractComposition,
    Bypass,
    NonDifferentiable,
    Parallel,
    Prediction,
    Residual,
    Sequential,
    Solver,
    select,
)

DATA_VERSION = 1  # bump when a generator changes, so cached data are regenerated


def _exponax_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("exponax")
    except PackageNotFoundError:
        return "none"


def windows(u: np.ndarray, m: int) -> np.ndarray:
    """All overlapping windows of m+1 frames: (S, T+1, …) → (S·(T+1−m), m+1, …)."""
    s, t1 = u.shape[:2]
    starts = np.arange(t1 - m)
    index = starts[:, None] + np.arange(m + 1)[None, :]  # (T+1−m, m+1)
    return u[:, index].reshape(s * len(starts), m + 1, *u.shape[2:])


@eqx.filter_jit
def solver_rollout(solver, u0, n: int):
    """``(u_n, frames (n, B, …))``: ``n`` steps of ``solver(u, cond)`` from a batch u0
    (data generation)."""

    def body(u, _):
        u = jax.vmap(lambda v: solver(v, None))(u)
        return u, u

    return jax.lax.scan(body, u0, None, length=n)


class AbstractTimeStepper(AbstractProblem):
    """A neural time-stepper problem: the rollout, data windows, metrics and open-loop
    contract, implemented once.

    Equinox's abstract/final pattern (as :class:`~physgrad.problems.oscillators.AbstractOscillators`):
    the settings are abstract fields that each final problem declares with its own paper's
    values; a final problem adds its physics (:meth:`generate`, :meth:`solvers`,
    :meth:`make_network`, :meth:`apply`) and nothing here is overridden.

    Fields:
        composition: how the network and the solver make one step
            (:class:`~physgrad.problems.sim.steppers.Prediction`, :class:`~physgrad.problems.sim.steppers.Residual`,
            :class:`~physgrad.problems.sim.steppers.Parallel`, :class:`~physgrad.problems.sim.steppers.Sequential`,
            :class:`~physgrad.problems.sim.steppers.Bypass`).
        m: the unrolled steps per training window.
        eval_horizon: the steps the metrics score.
        data_seed: the seed of the reference trajectories (the run's seed draws the network).
        differentiable_solver: false treats the solver as an external code without
            derivatives (:class:`~physgrad.problems.sim.steppers.NonDifferentiable`).
        zero_init: the network's last layer starts at zero, so a corrector starts as the bare
            solver (and a residual predictor as the identity); false: the paper's initialisation.
    """

    composition: eqx.AbstractVar[AbstractComposition]
    m: eqx.AbstractVar[int]
    eval_horizon: eqx.AbstractVar[int]
    data_seed: eqx.AbstractVar[int]
    differentiable_solver: eqx.AbstractVar[bool]
    zero_init: eqx.AbstractVar[bool]

    default_batch_size: ClassVar[int] = 16
    default_eval_samples: ClassVar[int] = 512
    # Windows are stored trajectory by trajectory, so a fixed order would make every batch
    # consecutive, overlapping windows of one trajectory; the authors' code permutes every
    # epoch (KS: per domain size, ``KuramotoSivashinsky.batch_group_key``; Kolmogorov:
    # one permutation of all windows; trainax: a fresh permutation per epoch).
    default_shuffle: ClassVar[bool] = True
    state_channels: ClassVar[int] = 1
    # α of the paper's parallel and bypass compositions: the command line's
    # ``composition=parallel|bypass`` builds them with it.
    network_scale: ClassVar[float] = 1.0

    def __check_init__(self):
        if not isinstance(self.composition, AbstractComposition):
            raise TypeError(
                f"composition must be a physgrad.problems.sim.steppers composition (Prediction(), Residual(), Parallel(scale), "
                f"Sequential(), Bypass(scale)), got {self.composition!r}"
            )
        if self.m < 1:
            raise ValueError(f"m must be >= 1, got {self.m}")

    # --- what a subclass defines ---------------------------------------------------------
    @abc.abstractmethod
    def generate(self, split: str) -> dict[str, np.ndarray]:
        """Reference trajectories of a split: ``{"u": (S, T+1, C, *N), "cond": (S,),
        "index": (S,)}`` (float32, float32, int32), ``index`` selecting the solver."""

    @abc.abstractmethod
    def solvers(self) -> Solver | tuple[Any, Any]:
        """The coarse solver, stacked over conditions (:func:`physgrad.problems.sim.steppers.stack_solvers`),
        or a single :class:`~physgrad.problems.sim.steppers.Solver` used for every sample."""

    @abc.abstractmethod
    def apply(self, network, u, cond):
        """The network's output for one state and its conditioning value (state-shaped)."""

    @property
    def solver_differentiable(self) -> bool:
        """The coarse solver's declaration (False when ``differentiable_solver=false``)."""
        return self._differentiable(self.solvers())

    def _differentiable(self, solvers) -> bool:
        """``solver_differentiable`` for solvers already built (building KS's costs ten
        exponax constructions, so :meth:`system` does not build them twice)."""
        declared = type(solvers[1] if isinstance(solvers, tuple) else solvers).differentiable
        return declared and self.differentiable_solver

    def data_settings(self) -> dict:
        """The settings that may change the generated data (the cache key): all but the
        stepper's and the network's (``m`` and ``eval_horizon`` stay: split lengths depend
        on them)."""
        skip = {"composition", "setup", "differentiable_solver", "zero_init"} | set(self.training_only_settings)
        return {k: getattr(self, k) for k in self.settings() if k not in skip}

    training_only_settings: ClassVar[tuple[str, ...]] = ()

    @property
    def zero_output_layer(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        """``zero_init``: the network's output layer starts at zero
        (:meth:`AbstractProblem.initial_network`)."""
        return self.zero_init

    # --- data ------------------------------------------------------------------------------
    def trajectories(self, split: str) -> dict[str, np.ndarray]:
        """A split's reference trajectories, generated once and cached on disk."""
        key = {"problem": self.name, "split": split, "version": DATA_VERSION, "exponax": _exponax_version(),
               **self.data_settings()}  # fmt: skip
        return cached_arrays(f"{self.name}-{split}", key, lambda: self.generate(split))

    def make_data(self, key):
        del key  # the data are fixed by data_seed; the run seed initialises the network
        train = self.trajectories("train")
        n_windows = train["u"].shape[1] - self.m
        if n_windows < 1:
            raise ValueError(f"training trajectories of {train['u'].shape[1]} frames are too short for m = {self.m}")
        out = {
            "train": {
                "u": jnp.asarray(windows(train["u"], self.m)),
                "cond": jnp.asarray(np.repeat(train["cond"], n_windows)),
                "index": jnp.asarray(np.repeat(train["index"], n_windows)),
            }
        }
        for split in ("val", "test"):
            out[split] = {k: jnp.asarray(v) for k, v in self.trajectories(split).items()}
        return out

    # --- the stepper and the rollout system -----------------------------------------------
    def step(self, network_fn, u_net, u_phys, cond, index, solvers=None):
        """One stepper step of one sample: ``(u⁺, ok)``; ``network_fn(u, cond)``."""
        solver = None
        if self.composition.uses_solver:
            solvers = self.solvers() if solvers is None else solvers
            solver = select(solvers, index) if isinstance(solvers, tuple) else solvers
            if not self.differentiable_solver:
                solver = NonDifferentiable(solver)
        return self.composition(solver, network_fn, u_net, u_phys, cond)

    def system(self, apply, m: int | None = None, teacher_forcing: bool = False) -> System:
        """The rollout :class:`~physgrad.rollout.System` over a batch of windows, with
        ``apply(params, u, cond)`` the network on its trainable parameters. The state is
        ``{"u", "traj", "cond", "index", "ok"}``; with ``teacher_forcing`` every step starts
        from the reference frame ũᵏ (the one-step modality)."""
        m = self.m if m is None else m
        if not 1 <= m <= self.m:
            raise ValueError(f"a rollout of {m} steps does not fit the problem's windows of m = {self.m}")
        solvers = self.solvers() if self.composition.uses_solver else None

        def transition(params, s_net, s_phys, k):
            u_net = s_net["traj"][:, k] if teacher_forcing else s_net["u"]
            u_phys = s_phys["traj"][:, k] if teacher_forcing else s_phys["u"]

            def one(un, up, cond, index):
                return self.step(lambda u, c: apply(params, u, c), un, up, cond, index, solvers)

            u_next, ok = jax.vmap(one)(u_net, u_phys, s_phys["cond"], s_phys["index"])
            target = s_phys["traj"][:, k + 1]
            loss = jnp.mean((u_next - target) ** 2)
            return {**s_phys, "u": u_next, "ok": s_phys["ok"] & ok}, loss

        def init(batch):
            b = batch["u"].shape[0]
            return {"u": batch["u"][:, 0], "traj": batch["u"], "cond": batch["cond"], "index": batch["index"],
                    "ok": jnp.ones((b,), bool)}  # fmt: skip

        weights = jnp.full((m,), 1.0 / m, jnp.float32)
        differentiable = not self.composition.uses_solver or self._differentiable(solvers)
        return System(transition, m, weights, init, differentiable)

    def check_refinable(self):
        if not self.composition.uses_solver:
            raise NotRefinable(self.composition)

    def rollout_pieces(self, static):
        """Beside the open-loop pieces of :meth:`~physgrad.problems.AbstractProblem.objective`:
        the rollout over the problem's m steps and the unrolled windows of any m
        (ONE / NOG / WIG); ``differentiable`` is the solver's declaration."""

        def apply(p, u, cond):
            return self.apply(eqx.combine(p, static), u, cond)

        def unrolled(m=None, teacher_forcing=False):
            return self.system(apply, m, teacher_forcing)

        rollout = unrolled()
        return {"rollout": rollout, "unrolled": unrolled, "differentiable": rollout.differentiable_physics}

    # --- the open-loop contract and the metrics -------------------------------------------
    def network_output(self, network, sample):
        """The autoregressive rollout u¹…u^T from ũ⁰ over the whole sample (T, C, *N)."""
        solvers = self.solvers() if self.composition.uses_solver else None
        fn = lambda u, c: self.apply(network, u, c)  # noqa: E731

        def body(u, _):
            u_next, _ = self.step(fn, u, u, sample["cond"], sample["index"], solvers)
            return u_next, u_next

        _, states = loops.scan(body, sample["u"][0], None, length=sample["u"].shape[0] - 1)
        return states

    def simulate(self, x, sample):
        return x

    def loss(self, y, sample):
        m = min(self.m, y.shape[0])
        return jnp.mean((y[:m] - sample["u"][1 : m + 1]) ** 2)

    def metrics(self, x, y, sample):
        steps = y.shape[0]
        if steps < self.eval_horizon:
            return {}
        h = self.eval_horizon
        ref = sample["u"][1:]
        err = (y[:h] - ref[:h]) ** 2
        rel = jnp.minimum(jnp.mean(err) / jnp.max(ref[:h] ** 2), 30.0)
        axes = tuple(range(1, y.ndim))
        nrmse = jnp.mean(jnp.sqrt(jnp.sum(err, axis=axes) / jnp.sum(ref[:h] ** 2, axis=axes)))
        nrmse = jnp.where(jnp.isfinite(nrmse), nrmse, jnp.inf)
        centred = lambda a: a - jnp.mean(a, axis=axes, keepdims=True)  # noqa: E731
        yc, rc = centred(y), centred(ref)
        corr = jnp.sum(yc * rc, axis=axes) / jnp.sqrt(jnp.sum(yc**2, axis=axes) * jnp.sum(rc**2, axis=axes) + 1e-30)
        corr = jnp.where(jnp.isfinite(corr), corr, -1.0)
        below = corr < 0.2
        corr_time = jnp.where(jnp.any(below), jnp.argmax(below), steps)
        blown = ~jnp.isfinite(y) | (jnp.abs(y) > 100 * jnp.max(jnp.abs(ref)))
        return {
            "rel_error": jnp.where(jnp.isfinite(rel), rel, 30.0),
            "nrmse": nrmse,
            "corr_time": corr_time.astype(jnp.float32),
            "diverged": jnp.any(blown).astype(jnp.float32),
        }

    def with_cond_channel(self, u, cond):
        """The state with its conditioning value appended as a constant channel."""
        return jnp.concatenate([u, jnp.full_like(u[:1], cond)], axis=0)


# The names of the deprecated string spellings (one release): the command line's own
# translation is physgrad.harness.objects'.
_DEPRECATED_COMPOSITIONS = {
    ("prediction", ""): Prediction,
    ("prediction", "full"): Prediction,
    ("prediction", "residual"): Residual,
    ("correction", "parallel"): Parallel,
    ("correction", "sequential"): Sequential,
    ("correction", "bypass"): Bypass,
}


class TimeStepperProblem(AbstractTimeStepper):
    """A base for a user's own time-stepper: :class:`AbstractTimeStepper` with its settings at
    the common defaults (``composition=Parallel(1.0)``, ``m=3``, ``eval_horizon=12``,
    ``data_seed=0``, ``differentiable_solver=True``, ``zero_init=False``). Subclass it with
    :meth:`generate`, :meth:`solvers`, :meth:`make_network` and :meth:`apply`.

    ``setup="prediction"|"correction"`` and ``composition="full"|"residual"|"parallel"|
    "sequential"|"bypass"`` (strings) still work for one release, with a
    ``DeprecationWarning``; pass a composition object instead.
    """

    composition: AbstractComposition = eqx.field(static=True, default=Parallel(1.0))
    m: int = eqx.field(static=True, default=3)
    eval_horizon: int = eqx.field(static=True, default=12)
    data_seed: int = eqx.field(static=True, default=0)
    differentiable_solver: bool = eqx.field(static=True, default=True)
    zero_init: bool = eqx.field(static=True, default=False)
    setup: str | None = eqx.field(static=True, default=None)  # deprecated: the composition's setup

    def __post_init__(self):
        if self.setup is None and not isinstance(self.composition, str):
            return
        warn_deprecated(
            "TimeStepperProblem(setup=..., composition='...') is deprecated; pass a composition object, "
            "e.g. composition=physgrad.problems.sim.steppers.Parallel(1.0) or Prediction()"
        )
        name = self.composition if isinstance(self.composition, str) else ""
        setup = self.setup or ("prediction" if name in ("full", "residual") else "correction")
        if (setup, name) == ("correction", ""):
            composition = self.composition if not isinstance(self.composition, str) else Parallel(self.network_scale)
        elif (setup, name) in _DEPRECATED_COMPOSITIONS:
            cls = _DEPRECATED_COMPOSITIONS[setup, name]
            composition = cls(self.network_scale) if cls in (Parallel, Bypass) else cls()
        else:
            raise ValueError(f"unknown composition {name!r} for the {setup} setup")
        self.composition = composition
        self.setup = None

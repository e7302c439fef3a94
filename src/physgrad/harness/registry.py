"""Names for the command line: methods and problems by name, built from flat settings.

This is the only place where update rules and their strategies are strings. A factory
takes the method's hyperparameters as keyword-only arguments with defaults (the command
line reads them with ``inspect.signature``) and returns an engine method
(:class:`physgrad.methods.AbstractMethod`) built from the library's objects; its
docstring's first line describes it. The factories are private and named by the table
:data:`METHODS` alone, so a name such as ``hig`` means one thing in the library (the
estimator :func:`physgrad.hig`). The batch size is a training setting (per-method
defaults come from the problem).
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable
from typing import Any

import optax
import optax.contrib

from .. import routes
from ..inverse import LBFGS, Analytic, GaussNewton, LinearSolve, SaddleFreeNewton
from ..methods import (
    AbstractMethod,
    Gradient,
    JacobianPower,
    LevenbergMarquardt,
    Method,
    Newton,
    RolloutGradient,
    ScaleInvariantPhysics,
    Unrolled,
    UnrolledGradient,
)
from ..methods.averaged_kronecker import AveragedKronecker
from ..methods.eigen_kronecker import EigenCorrectedKronecker
from ..methods.kfac import kfac
from ..methods.kronecker_hig import KroneckerPower
from ..methods.sip import L1Proxy, L2Proxy
from ..methods.unrolling import Plateau
from ..rollout import Combined, M, R, S
from . import objects
from .papers import protocol
from .plugins import METHOD_GROUP, PROBLEM_GROUP, Registry, method_factory, problem_class
from .zoo import OPTAX_MODULES, is_optax_name, optax_method, optax_names  # noqa: F401  (their names here too)

# `# isort: skip`: isort would split this compact `# fmt: skip` import into one name a line
from ..problems import (  # isort: skip
    AbstractProblem, Advection1d, CartPole, ExpInverse, Guidance, Heat, HigToy, Kolmogorov, KuramotoSivashinsky,
    LinearOscillators, NavierStokes, Oscillators, Poisson, PoissonHig, QuantumControl, QuantumDipole, Sine, Toy2d,
)  # fmt: skip

# --- DP: optax optimizers on the DP gradient --------------------------------------------
# ε = 1e-7 is the Keras default that the HIG and StableBPTT papers' baselines used.


def _adam(*, lr: float = 1e-3, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-7):
    """Adam on DP gradients (Kingma & Ba 2015; Keras ε = 1e-7)."""
    return Method(Gradient(), optax.adam(lr, b1=b1, b2=b2, eps=eps))


def _sgd(*, lr: float = 1e-2, momentum: float = 0.0):
    """Plain (or momentum) SGD on DP gradients: θ ← θ − η ∇L."""
    return Method(Gradient(), optax.sgd(lr, momentum=momentum or None))


def _rmsprop(*, lr: float = 1e-3, decay: float = 0.9, eps: float = 1e-7):
    """RMSprop on DP gradients (Tieleman & Hinton 2012; Keras defaults)."""
    return Method(Gradient(), optax.rmsprop(lr, decay=decay, eps=eps))


def _adagrad(*, lr: float = 1e-2, initial_accumulator: float = 0.1, eps: float = 1e-7):
    """Adagrad on DP gradients (Duchi et al. 2011; lr 1e-2 and accumulator 0.1: physgrad's choice)."""
    return Method(Gradient(), optax.adagrad(lr, initial_accumulator_value=initial_accumulator, eps=eps))


def _adadelta(*, lr: float = 1.0, rho: float = 0.95, eps: float = 1e-7):
    """Adadelta on DP gradients (Zeiler 2012: η = 1, ρ = 0.95)."""
    return Method(Gradient(), optax.adadelta(lr, rho=rho, eps=eps))


# The DP optimizers with their defaults above, by name, for methods that apply an optax
# optimizer to some other direction (SIP's proxy gradient): name -> (lr -> transformation).
_DP = {"adam": _adam, "sgd": _sgd, "rmsprop": _rmsprop, "adagrad": _adagrad, "adadelta": _adadelta}
OPTIMIZERS = {name: (lambda lr, f=f: f(lr=lr).optimizer) for name, f in _DP.items()}

# --- Gauss–Newton and HIG ---------------------------------------------------------------
# The route names of the command line and the route objects they stand for: the one table
# of them (the library speaks route objects, physgrad.routes).
_ROUTES: dict[str, Callable[[int, int], routes.AbstractRoute]] = {
    "auto": lambda blocks, steps: routes.Auto(),
    "svd": lambda blocks, steps: routes.SVD(),
    "gram": lambda blocks, steps: routes.Gram(),
    "structured": lambda blocks, steps: routes.Structured(),
    "blockgram": lambda blocks, steps: routes.BlockGram(blocks),
    "lanczos": lambda blocks, steps: routes.Lanczos(steps),
}
ROUTES = tuple(_ROUTES)


def make_route(name: str, *, blocks: int = 8, lanczos_steps: int = 64) -> routes.AbstractRoute:
    """A half-inverse route object by name (``blocks`` and ``lanczos_steps`` go to the
    routes that use them)."""
    _choose("route", name, ROUTES)
    return _ROUTES[name](blocks, lanczos_steps)


def _hig(*, lr: float = 1.0, truncation: float = 1e-6, route: str = "auto", blocks: int = 8, lanczos_steps: int = 64):
    """Half-inverse gradients: −η V Σ^{-1/2} Uᵀ g, applied by SGD (Schnell et al. 2022).

    ``route``: ``svd``/``gram`` hold J; ``structured`` (exact, from each dense layer's
    factors; ``auto`` picks it for networks with dense layers), ``blockgram`` (exact,
    ``blocks`` sample groups) and ``lanczos`` (approximate, ``lanczos_steps``) never form it."""
    _check_route_sizes(blocks, lanczos_steps)
    rule = JacobianPower(-0.5, truncation, make_route(route, blocks=blocks, lanczos_steps=lanczos_steps))
    return Method(rule, optax.sgd(lr))


def _gn(*, lr: float = 1.0, truncation: float = 1e-6, route: str = "auto", blocks: int = 8, lanczos_steps: int = 64):
    """Gauss–Newton: −η J⁺ g (pseudo-inverse, κ = −1) with the same truncation, by SGD."""
    _check_route_sizes(blocks, lanczos_steps)
    rule = JacobianPower(-1.0, truncation, make_route(route, blocks=blocks, lanczos_steps=lanczos_steps))
    return Method(rule, optax.sgd(lr))


def _lm(*, lr: float = 1.0, damping: float = 1e-3, truncation: float = 1e-6, route: str = "auto", blocks: int = 8,
       lanczos_steps: int = 64, reject: bool = True):  # fmt: skip
    """Levenberg–Marquardt: −η Jᵀ(J Jᵀ + λI)⁻¹ g, λ = μ σ_max², μ by Nielsen's gain-ratio rule (rejects bad steps)."""
    _check_route_sizes(blocks, lanczos_steps)
    rule = JacobianPower(-1.0, truncation, make_route(route, blocks=blocks, lanczos_steps=lanczos_steps))
    return LevenbergMarquardt(rule, optax.sgd(lr), damping=damping, reject=reject)  # pyright: ignore[reportCallIssue]  (acceptance is a property)


def _khig(*, lr: float = 1.0, power: float = -0.75, truncation: float = 1e-6, damping: float = 1e-4,
          explicit_max: int = 1024, curvature_ema: float = 0.0, inverse_every: int = 1, curvature_every: int = 1,
          probes: int = 0):  # fmt: skip
    """Kronecker-factored HIG: −η b^{−p} G^p ∇W A^p per dense layer (K-FAC's factors, HIG's power p = −3/4), by SGD.

    ``power`` −1 is Kronecker-factored Gauss–Newton; ``truncation`` τ drops eigenvalue products
    λ_G λ_A ≤ τ² of the block's largest (HIG's σ ≤ τ σ_max, λ ≈ σ²); ``damping`` adds
    damping·λ_max before the power (0: the pure analogue, equal to HIG where the factors are
    exact, diverges off that case); parameters outside the dense layers it sees form one
    exact block, refused beyond an ``explicit_max``-wide eigendecomposition; convolutions get
    KFC's factors; ``probes`` s > 0 estimates G from s random output directions per sample
    instead of every output row (fields of outputs: the U-Nets). The factors are fresh per batch (HIG's way) unless ``curvature_ema`` β > 0
    or ``inverse_every`` k > 1: then running averages β·old + (1 − β)·new, eigendecomposed
    every k steps (K-FAC's way), the factors collected every ``curvature_every`` steps (a divisor of k;
    on conv layers and with probes the other steps cost a plain gradient)."""
    rule = KroneckerPower(power, truncation, damping, explicit_max, probes)
    if curvature_ema == 0.0 and inverse_every == 1 and curvature_every == 1:
        return Method(rule, optax.sgd(lr))
    return AveragedKronecker(
        rule, optax.sgd(lr), curvature_ema=curvature_ema, inverse_every=inverse_every, curvature_every=curvature_every
    )  # pyright: ignore[reportCallIssue]  (control is a property)


# KHIG at the other two powers of the power ablation (issue 51), as names of their own so that
# one bench or tuned bench ranks the three powers side by side, each step timed in the same
# calibration sitting (a --set khig.power=... changes khig everywhere in a bench). Everything
# but the power is khig's, defaults and search space included.
def _kgn(*, lr: float = 1.0, truncation: float = 1e-6, damping: float = 1e-4, explicit_max: int = 1024,
         curvature_ema: float = 0.0, inverse_every: int = 1, curvature_every: int = 1, probes: int = 0):  # fmt: skip
    """Kronecker-factored Gauss–Newton: ``khig`` at power −1, −η b G^{−1} ∇W A^{−1} per layer (settings as ``khig``)."""
    return _khig(lr=lr, power=-1.0, truncation=truncation, damping=damping, explicit_max=explicit_max,
                 curvature_ema=curvature_ema, inverse_every=inverse_every, curvature_every=curvature_every,
                 probes=probes)  # fmt: skip


def _khig_half(*, lr: float = 1.0, truncation: float = 1e-6, damping: float = 1e-4, explicit_max: int = 1024,
               curvature_ema: float = 0.0, inverse_every: int = 1, curvature_every: int = 1, probes: int = 0):  # fmt: skip
    """KHIG at power −½: ``khig`` with −η b^{½} G^{−½} ∇W A^{−½} per layer, the power ablation's third arm (settings as ``khig``)."""
    return _khig(lr=lr, power=-0.5, truncation=truncation, damping=damping, explicit_max=explicit_max,
                 curvature_ema=curvature_ema, inverse_every=inverse_every, curvature_every=curvature_every,
                 probes=probes)  # fmt: skip


def _ekhig(*, lr: float = 1.0, power: float = -0.75, truncation: float = 1e-6, damping: float = 1e-4,
           explicit_max: int = 1024, basis_every: int = 1):  # fmt: skip
    """Eigenvalue-corrected KHIG: KHIG's Kronecker eigenbasis per dense layer, its eigenvalues replaced by the exact Gauss–Newton diagonal there, by SGD.

    Λ_ij = Σ_{s,k} (U_Gᵀ g_{s,k})_i² (U_Aᵀ ā_s)_j² raised to ``power`` with KHIG's ``truncation``
    and ``damping``; the bases are recomputed every ``basis_every`` steps (EKFAC's correction)."""
    rule = KroneckerPower(power, truncation, damping, explicit_max)
    return EigenCorrectedKronecker(rule, optax.sgd(lr), basis_every=basis_every)  # pyright: ignore[reportCallIssue]  (control is a property)


def _kfac_hig(*, adaptive: bool = True, lr: float = 1e-3, momentum: float = 0.9, damping: float = 1e-3,
              adaptive_damping: bool = True, curvature_ema: float = 0.95, inverse_every: int = 5,
              estimation: str = "ggn_exact", loss_hessian: str = "auto", precon_power: float = -0.75, seed: int = 0):  # fmt: skip
    """K-FAC (kfac-jax) at HIG's power: (Ĝ + λI)^{−3/4} ∇L on the exact Gauss–Newton Kronecker blocks, inverted exactly.

    kfac-jax's ``precon_power`` (since 2024-08) with ``ggn_exact`` estimation: what kfac-jax
    had of KHIG (fresh, undamped, lr 1: KHIG's direction times b^{3/4}); settings as ``kfac``."""
    return kfac(adaptive=adaptive, lr=lr, momentum=momentum, damping=damping, adaptive_damping=adaptive_damping,
                curvature_ema=curvature_ema, inverse_every=inverse_every, estimation=estimation,
                loss_hessian=loss_hessian, exact_inverses=True, precon_power=precon_power, seed=seed)  # fmt: skip


def _check_route_sizes(blocks, lanczos_steps):
    if blocks < 1 or lanczos_steps < 1:
        raise ValueError(f"blocks and lanczos_steps must be >= 1, got {blocks} and {lanczos_steps}")


def _newton(*, lr: float = 1.0, damping: float = 0.0):
    """Newton's method with the dense Hessian of the batch loss: −η (H + λI)⁻¹ ∇L (small problems)."""
    return Method(Newton(damping), optax.sgd(lr))


# --- SIP ---------------------------------------------------------------------------------
INVERSE_SOLVERS = ("auto", "analytic", "gauss_newton", "saddle_free_newton", "lbfgs", "linear_solve")


def make_solver(name: str, *, analytic=None, rcond=1e-5, max_loss_change=0.2, max_steps=100, tol=1e-6, krylov="gmres",
                accept_last=False):  # fmt: skip
    """A local inverse solver by name; ``auto`` is ``analytic`` when ``analytic`` (a
    problem's inverse function) is given, else Gauss–Newton. ``analytic`` with no function
    stands for the problem's own inverse, bound by SIP. ``max_loss_change <= 0`` disables
    the saddle-free Newton limit."""
    _choose("inverse solver", name, INVERSE_SOLVERS)
    if name == "auto":
        name = "analytic" if analytic is not None else "gauss_newton"
    if name == "analytic":
        return Analytic(analytic)
    if name == "gauss_newton":
        return GaussNewton(rcond)
    if name == "saddle_free_newton":
        return SaddleFreeNewton(max_loss_change if max_loss_change > 0 else None)
    if name == "lbfgs":
        return LBFGS(max_steps, tol, accept_last)
    return LinearSolve(**objects.krylov(krylov), rtol=tol, max_steps=max_steps)


SIP_PROXIES = {"l2": L2Proxy(), "l1": L1Proxy()}


def _sip(
    *,
    lr: float = 1e-3,
    optimizer: str = "adam",
    eta: float = 1.0,
    proxy: str = "l2",
    solver: str = "auto",
    rcond: float = 1e-5,
    max_loss_change: float = 0.2,
    max_steps: int = 100,
    tol: float = 1e-6,
    krylov: str = "gmres",
    precision: str = "float32",
    accept_last: bool = False,
):
    """Scale-invariant physics: fit the network to a local inverse x̃ = P⁻¹(y + η(y* − y); x) (Holl et al. 2022)."""
    _choose("optimizer", optimizer, OPTIMIZERS)
    settings: dict[str, Any] = dict(rcond=rcond, max_loss_change=max_loss_change, max_steps=max_steps, tol=tol, krylov=krylov,
                    accept_last=accept_last)  # fmt: skip
    inverse = None if solver == "auto" else make_solver(solver, **settings)  # auto: decided by the problem
    if solver == "auto":
        make_solver("gauss_newton", **settings)  # the fallback's settings are checked now
    _choose("proxy", proxy, SIP_PROXIES)
    _choose("precision", precision, ("float32", "float64"))
    return Method(ScaleInvariantPhysics(inverse, eta, SIP_PROXIES[proxy], precision), OPTIMIZERS[optimizer](lr))


# --- BPTT and stabilised BPTT --------------------------------------------------------------
CLIP_MODES = ("value", "norm", "none")


def clipping(mode: str, threshold: float) -> optax.GradientTransformation:
    """The StableBPTT authors' clip modes as optax transformations (before the optimizer):
    ``value`` = Keras ``clipvalue`` (element-wise), ``norm`` = ``global_clipnorm``."""
    _choose("clip mode", mode, CLIP_MODES)
    if threshold <= 0:
        raise ValueError(f"clip_threshold must be positive, got {threshold}")
    return {"value": optax.clip(threshold), "norm": optax.clip_by_global_norm(threshold), "none": optax.identity()}[
        mode
    ]


def _rollout_method(policy, clip, clip_threshold, lr, eps, checkpoint):
    return Method(
        RolloutGradient(policy, checkpoint), optax.chain(clipping(clip, clip_threshold), optax.adam(lr, eps=eps))
    )


def _bptt(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
         truncate: int = 0, warmup: int = 0, checkpoint: bool = False):  # fmt: skip
    """Full BPTT (R): the true rollout gradient, clipped, Adam; truncate=k cuts every k steps."""
    return _rollout_method(R(truncate=truncate, warmup=warmup), clip, clip_threshold, lr, eps, checkpoint)


def _sbptt_m(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
            truncate: int = 0, warmup: int = 0, checkpoint: bool = False):  # fmt: skip
    """Stabilised BPTT's modified gradient (M): stop-gradient on the network's input only."""
    return _rollout_method(M(truncate=truncate, warmup=warmup), clip, clip_threshold, lr, eps, checkpoint)


def _no_temporal(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
                warmup: int = 0, checkpoint: bool = False):  # fmt: skip
    """No temporal gradient (S): stop-gradient on network and physics inputs (one-step gradients)."""
    return _rollout_method(S(warmup=warmup), clip, clip_threshold, lr, eps, checkpoint)


def _sbptt_c(*, clip: str = "value", clip_threshold: float = 1.0, lr: float = 1e-3, eps: float = 1e-7,
            one_pass: bool = True, checkpoint: bool = False):  # fmt: skip
    """Stabilised BPTT (C, Schnell & Thuerey 2024): M's gradient masked by the signs of R's."""
    return _rollout_method(Combined(M(), R(), one_pass=one_pass), clip, clip_threshold, lr, eps, checkpoint)


# --- ONE / NOG / WIG -----------------------------------------------------------------------
def parse_list(text: str, kind, name: str) -> tuple:
    """A list setting (``"1,2,4"``, or ``"1/2/4"`` inside ``compare``, where a comma sweeps) as
    a tuple; a one-line error otherwise."""
    try:
        return tuple(kind(t) for t in re.split(r"[,/]", str(text)) if t.strip())
    except ValueError:
        raise ValueError(f"{name} must be a list of numbers separated by ',' or '/', got {text!r}") from None


def _unrolled(policy, teacher_forcing, *, m, checkpoint=False, curriculum="", stage_lr="", plateau_factor=0.0,
              plateau_patience=10, plateau_cooldown=0, plateau_every=0, **options):  # fmt: skip
    rule = UnrolledGradient(policy, teacher_forcing, m, checkpoint)
    # plateau_factor 0: no plateau schedule (the default); else physgrad.methods.unrolling.Plateau
    plateau = Plateau(plateau_every, plateau_factor, plateau_patience, plateau_cooldown) if plateau_factor else None
    return Unrolled(
        rule,
        curriculum=parse_list(curriculum, int, "curriculum"),
        stage_lr=parse_list(stage_lr, float, "stage_lr"),
        plateau=plateau,
        **options,
    )


def _one(*, lr: float = 1e-3, lr_warmup: int = 0, decay: float = 1.0, decay_every: int = 0, clip: float = 0.0,
        skip_nan: bool = True, norm_guard: bool = False, skip_solver_failure: bool = True, m: int = 0,
        plateau_factor: float = 0.0, plateau_patience: int = 10, plateau_cooldown: int = 0,
        plateau_every: int = 0):  # fmt: skip
    """One-step training (ONE): every step from the reference frame; B·m targets per update."""
    return _unrolled(S(), True, m=m, lr=lr, lr_warmup=lr_warmup, decay=decay, decay_every=decay_every, clip=clip,
                     skip_nan=skip_nan, norm_guard=norm_guard, skip_solver_failure=skip_solver_failure,
                     plateau_factor=plateau_factor, plateau_patience=plateau_patience,
                     plateau_cooldown=plateau_cooldown, plateau_every=plateau_every)  # fmt: skip


def _nog(*, lr: float = 1e-3, lr_warmup: int = 0, decay: float = 1.0, decay_every: int = 0, clip: float = 0.0,
        skip_nan: bool = True, norm_guard: bool = False, skip_solver_failure: bool = True, m: int = 0,
        curriculum: str = "", stage_epochs: float = 1.0, stage_lr: str = "", checkpoint: bool = False,
        plateau_factor: float = 0.0, plateau_patience: int = 10, plateau_cooldown: int = 0,
        plateau_every: int = 0):  # fmt: skip
    """No-gradient unrolling (NOG): m-step rollout, stop-gradient on each state after its loss."""
    return _unrolled(S(), False, m=m, lr=lr, lr_warmup=lr_warmup, decay=decay, decay_every=decay_every, clip=clip,
                     skip_nan=skip_nan, norm_guard=norm_guard, skip_solver_failure=skip_solver_failure,
                     curriculum=curriculum, stage_epochs=stage_epochs, stage_lr=stage_lr, checkpoint=checkpoint,
                     plateau_factor=plateau_factor, plateau_patience=plateau_patience,
                     plateau_cooldown=plateau_cooldown, plateau_every=plateau_every)  # fmt: skip


def _wig(*, lr: float = 1e-3, lr_warmup: int = 0, decay: float = 1.0, decay_every: int = 0, clip: float = 0.0,
        skip_nan: bool = True, norm_guard: bool = False, skip_solver_failure: bool = True, m: int = 0,
        truncate: int = 0, warmup: int = 0, curriculum: str = "", stage_epochs: float = 1.0, stage_lr: str = "",
        checkpoint: bool = False, plateau_factor: float = 0.0, plateau_patience: int = 10, plateau_cooldown: int = 0,
        plateau_every: int = 0):  # fmt: skip
    """Fully differentiable unrolling (WIG): BPTT through network and solver; truncate/warmup cuts."""
    return _unrolled(R(truncate=truncate, warmup=warmup), False, m=m, lr=lr, lr_warmup=lr_warmup, decay=decay,
                     decay_every=decay_every, clip=clip, skip_nan=skip_nan, norm_guard=norm_guard,
                     skip_solver_failure=skip_solver_failure, curriculum=curriculum, stage_epochs=stage_epochs,
                     stage_lr=stage_lr, checkpoint=checkpoint,
                     plateau_factor=plateau_factor, plateau_patience=plateau_patience,
                     plateau_cooldown=plateau_cooldown, plateau_every=plateau_every)  # fmt: skip


class _Methods(Registry[Callable[..., AbstractMethod]]):
    """The registered methods and the ``physgrad.methods`` plugins, plus every optax zoo
    name and import path looked up on demand (iteration gives the registered ones and the
    plugins only)."""

    def __contains__(self, name):
        if isinstance(name, str) and is_optax_name(name):
            return name in optax_names()
        return super().__contains__(name)

    def __missing__(self, name):
        if isinstance(name, str) and is_optax_name(name):
            return optax_method(name)
        return super().__missing__(name)


# The command line's problem names and their classes: the built-in problems, the problems of
# installed packages' ``physgrad.problems`` entry points, and any ``module:Class`` import path
# (physgrad.harness.plugins).
_BUILT_IN_PROBLEMS: dict[str, type[AbstractProblem]] = {
    cls.name: cls
    for cls in (
        HigToy,
        Oscillators,
        QuantumDipole,
        PoissonHig,
        LinearOscillators,
        Toy2d,
        ExpInverse,
        Sine,
        Poisson,
        Heat,
        NavierStokes,
        CartPole,
        Guidance,
        QuantumControl,
        KuramotoSivashinsky,
        Kolmogorov,
        Advection1d,
    )  # fmt: skip
}
PROBLEMS: Registry[type[AbstractProblem]] = Registry("problem", _BUILT_IN_PROBLEMS, PROBLEM_GROUP, problem_class)

# The command line's method names and their factories: the one table of them, with the
# ``physgrad.methods`` entry points' and import paths' factories (physgrad.harness.plugins).
# The factories are private (`_hig`), so `hig` means the library's estimator (physgrad.hig) alone.
METHODS: Registry[Callable[..., AbstractMethod]] = _Methods("method", {
    **_DP, "gn": _gn, "hig": _hig, "khig": _khig, "kgn": _kgn, "khig_half": _khig_half,
    "ekhig": _ekhig, "lm": _lm, "kfac": kfac, "kfac_hig": _kfac_hig,
    "sip": _sip, "newton": _newton, "bptt": _bptt, "sbptt_m": _sbptt_m, "sbptt_c": _sbptt_c,
    "no_temporal": _no_temporal, "one": _one, "nog": _nog, "wig": _wig,
}, METHOD_GROUP, method_factory)  # fmt: skip


# The Kronecker-factored HIG forms: their η, batch and τ mean HIG's, and default to HIG's.
KRONECKER_HIG = ("khig", "kgn", "khig_half", "ekhig")


def paper_defaults(problem: type[AbstractProblem], method: str) -> dict[str, Any]:
    """The paper's hyperparameters for ``method`` on ``problem`` (batch size included; the
    table is :data:`physgrad.harness.papers.PROTOCOLS`); ``lm`` takes Gauss–Newton's where
    the problem has none of its own, the Kronecker-factored HIG forms (:data:`KRONECKER_HIG`) HIG's, ``kfac`` and ``kfac_hig``
    Adam's batch size; an optax zoo entry takes Adam's batch size, and Adam's learning rate when optax asks for one."""
    table = protocol(getattr(problem, "name", "")).defaults

    def defaults_for(name: str) -> dict[str, Any]:
        return {"batch_size": problem.default_batch_size, **table.get(name, {})}

    if method == "lm" and method not in table:  # damped GN: GN's η, batch and τ
        return defaults_for("gn")
    if method in KRONECKER_HIG and method not in table:  # HIG's η, batch and τ (the same meaning)
        return defaults_for("hig")
    if method in ("kfac", "kfac_hig") and method not in table:  # its own adaptive step; Adam's batch
        return {"batch_size": defaults_for("adam")["batch_size"]}
    if not is_optax_name(method):
        return defaults_for(method)
    adam = defaults_for("adam")
    out = {"batch_size": adam["batch_size"]}
    if METHODS[method].lr_required and "lr" in adam:
        out["lr"] = adam["lr"]
    return out


def hyperparameters(method: str) -> dict[str, Any]:
    """A registered method's hyperparameters and their generic defaults."""
    params = inspect.signature(METHODS[method]).parameters
    return {name: p.default for name, p in params.items()}


def describe(method: str) -> str:
    """The one-line description of a registered method."""
    return (METHODS[method].__doc__ or "").strip().splitlines()[0]


def _choose(kind: str, name: str, choices) -> None:
    if name not in choices:
        raise ValueError(f"unknown {kind} {name!r}; valid choices: {', '.join(choices)}")


__all__ = ["INVERSE_SOLVERS", "METHODS", "OPTAX_MODULES", "OPTIMIZERS", "PROBLEMS", "ROUTES", "describe",
           "hyperparameters", "is_optax_name", "make_route", "make_solver", "optax_method", "optax_names", "paper_defaults"]  # fmt: skip

"""Scale-invariant physics (SIP) updates: train the network on a local physics inverse.

Source: Holl, Koltun, Thuerey, *Scale-invariant Learning by Physics Inversion*, NeurIPS
2022 (arXiv 2109.15048 v3, §3 and Algorithm 1); PBDL book, chapter "Scale-invariant
physics training".

Per mini-batch, with the network output x_i = f(y*_i; θ) and y_i = P(x_i):

    y_t,i = y_i + η (y*_i − y_i)                  (the Newton step of an L2 loss in y)
    x̃_i  = stop_gradient(P⁻¹(y_t,i; x_i))        (local inverse solver, per sample)
    L_proxy = (1/b) Σ_i ½ ‖x_i − x̃_i‖²            (L2Proxy; L1Proxy: (1/b) Σ_i Σ_j |x_ij − x̃_ij|)
    d = ∇_θ L_proxy                                (applied by any optax optimizer; Adam in the paper)

The simulator and the solver run on stop-gradient values outside the network's autodiff:
no gradient flows into the simulator (it may be non-differentiable, e.g. an external code,
when the solver does not need derivatives), and the inverse may run in float64
(``precision=jnp.float64``, scoped to the solve: the user's process keeps its settings).
A sample whose solve does not converge (or is not finite) gets x̃ = x, i.e. contributes
nothing, and is counted in the step's ``inverse_failures``. The authors sum the proxy over
the batch; physgrad averages (Adam is invariant to the factor; SGD's lr absorbs it). With
η = 1 and linear invertible P, x̃ = x* and SIP is supervised training (the paper's §3).
"""

from __future__ import annotations

import abc
import warnings
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..inverse import AbstractInverseSolver, Analytic, GaussNewton, InverseFailureWarning
from ..precision import float64_call, to_float64
from .base import ANALYTIC_INVERSE, SPLIT, AbstractRule, Estimator, Objective, Part, required

PRECISIONS = (np.dtype("float32"), np.dtype("float64"))


class AbstractProxy(eqx.Module):
    """The x-space proxy loss: ``proxy(x − x̃, b) -> (L_proxy, ∂L_proxy/∂x)``.

    ``x − x̃`` has shape (b, …); the cotangent is what the network's pullback receives, so
    the direction is ``d = Jᵀ ∂L_proxy/∂x`` with J the network's Jacobian (no simulator
    derivative: x̃ is a constant of the step)."""

    @abc.abstractmethod
    def __call__(self, diff: Array, batch_size: int) -> tuple[Array, Array]: ...


class L2Proxy(AbstractProxy):
    """``L = (1/b) Σ_i ½ ‖x_i − x̃_i‖²``, cotangent ``(x − x̃)/b``: the paper's proxy (Algorithm 1)."""

    def __call__(self, diff, batch_size):
        return 0.5 * jnp.sum(diff**2) / batch_size, diff / batch_size


class L1Proxy(AbstractProxy):
    """``L = (1/b) Σ_i Σ_j |x_ij − x̃_ij|``, cotangent ``sign(x − x̃)/b``: the paper's choice for
    the ill-conditioned sine inversion (Fig. 5), where a few large residuals would dominate L2."""

    def __call__(self, diff, batch_size):
        return jnp.sum(jnp.abs(diff)) / batch_size, jnp.sign(diff) / batch_size


class ScaleInvariantPhysics(AbstractRule):
    """``d = ∇_θ ½‖f(y*; θ) − x̃‖²`` with x̃ from a local physics inverse.

    ``solver=None`` picks the problem's analytic inverse when it has one, else
    :class:`~physgrad.inverse.GaussNewton`; ``Analytic()`` without a function uses the
    problem's inverse.

    ``warn_failures``: when more than this fraction of a batch's local solves fail, a
    :class:`~physgrad.inverse.InverseFailureWarning` is issued from inside the step (a
    ``jax.debug.callback`` that runs only then; Python shows it once per process by its
    default filter, ``warnings.simplefilter("error", InverseFailureWarning)`` makes it
    an exception); None: never. The count is ``stats["inverse_failures"]`` either way.
    """

    solver: AbstractInverseSolver | None = eqx.field(static=True, default=None)
    eta: float = eqx.field(static=True, default=1.0)
    proxy: AbstractProxy = eqx.field(static=True, default=L2Proxy())
    # the dtype of the local solve; any dtype specifier (jnp.float64, np.float64, "float64")
    precision: np.dtype = eqx.field(static=True, default=np.dtype("float32"), converter=np.dtype)
    warn_failures: float | None = eqx.field(static=True, default=0.5)

    def __check_init__(self):
        if not isinstance(self.proxy, AbstractProxy):
            raise ValueError(f"proxy must be L2Proxy() or L1Proxy() (physgrad.methods.sip), got {self.proxy!r}")
        if not self.eta > 0:
            raise ValueError(f"eta must be > 0 (the fraction of the y-space step), got {self.eta}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be float32 or float64, got {self.precision}")
        if self.solver is not None and not isinstance(self.solver, AbstractInverseSolver):
            raise ValueError(f"solver must be a physgrad.inverse solver object, got {self.solver!r}")
        if self.warn_failures is not None and not 0 <= self.warn_failures < 1:
            raise ValueError(f"warn_failures must be in [0, 1) or None, got {self.warn_failures}")

    def resolve_solver(self, objective) -> AbstractInverseSolver:
        """The solver with the problem's analytic inverse bound where it stands for it."""
        solver = self.solver
        if solver is None:
            solver = Analytic() if objective.inverse is not None else GaussNewton()
        if isinstance(solver, Analytic) and solver.fn is None:
            objective.require(ANALYTIC_INVERSE, self.name)  # refuses a problem without one
            solver = Analytic(objective.inverse)
        return solver

    name: ClassVar[str] = "sip"

    @property
    def part(self) -> Part:  # pyright: ignore[reportIncompatibleVariableOverride]
        """The network and the physics apart (:data:`~physgrad.methods.SPLIT`), and the
        problem's analytic inverse where ``Analytic()`` without a function stands for it."""
        if isinstance(self.solver, Analytic) and self.solver.fn is None:
            return ANALYTIC_INVERSE
        return SPLIT

    def __call__(self, objective, params, batch):
        network_output = required(objective.network_output, "network_output")
        x, pullback = jax.vjp(lambda p: jax.vmap(network_output, (None, 0))(p, batch), params)
        x0 = jax.lax.stop_gradient(x)
        y = jax.vmap(required(objective.simulate, "simulate"))(x0, batch)
        stats = {}
        if objective.loss is not None:
            stats["loss"] = jnp.mean(jax.vmap(objective.loss)(y, batch))
        x_tilde, ok = self.local_inverse(objective, x0, jax.lax.stop_gradient(y), batch)
        b = x.shape[0]
        diff = x0 - x_tilde
        proxy, cotangent = self.proxy(diff, b)
        (grads,) = pullback(cotangent.astype(x.dtype))
        stats.setdefault("loss", proxy)
        failures = jnp.sum(~ok)
        self.warn_if_failing(failures, b, self.resolve_solver(objective))
        return grads, {**stats, "proxy": proxy, "inverse_failures": failures}

    def warn_if_failing(self, failures, batch_size: int, solver: AbstractInverseSolver) -> None:
        """Issue :class:`~physgrad.inverse.InverseFailureWarning` from the running step when
        more than ``warn_failures`` of the batch failed. The host callback sits in a
        ``lax.cond`` branch, so a step whose solves succeed pays no host round trip. The
        message is the same at every step (the count is in the stats), so Python's
        default filter shows it once."""
        fraction = self.warn_failures
        if fraction is None:
            return

        def warn():  # no count in the message: one that varied would be shown at every step
            warnings.warn(
                f"SIP: more than {fraction:.0%} of a batch's local inverse solves ({type(solver).__name__}) failed "
                "and gave those samples no update (stats['inverse_failures'] counts them); loosen the solver's "
                "tolerance, raise max_steps, or use precision=jnp.float64",
                InverseFailureWarning,
                stacklevel=2,
            )

        jax.lax.cond(failures > fraction * batch_size, lambda: jax.debug.callback(warn), lambda: None)

    def local_inverse(self, objective, x, y, batch):
        """(x̃, converged) per sample; failed samples get x̃ = x.

        With ``precision=jnp.float64`` the solve is one :func:`physgrad.precision.float64_call`
        (traced, batched and lowered with 64-bit types on, also inside a user's ``jax.jit``
        with x64 off) and x̃ comes back in x's dtype."""
        solver = self.resolve_solver(objective)

        def solve(x, y, batch):
            # (1 − η) y + η y*, not y + η (y* − y): exactly y* at η = 1 even when y* ≪ y.
            y_target = (1 - self.eta) * y + self.eta * jax.vmap(objective.target)(batch)
            result = jax.vmap(lambda *a: solver(objective.simulate, *a))(x, y, y_target, batch)
            ok = result.converged & jnp.all(jnp.isfinite(result.x.reshape(x.shape[0], -1)), axis=1)
            return result.x, ok

        def solve_float64(x_, y_, batch_):  # casts inside the region: no float64 leaves it
            x_new, ok = solve(*to_float64((x_, y_, batch_)))
            return x_new.astype(x.dtype), ok

        if self.precision == np.float64:
            x_new, ok = float64_call(solve_float64, x, y, batch)
        else:
            x_new, ok = solve(x, y, batch)
        x_new = x_new.astype(x.dtype)
        mask = ok.reshape((-1,) + (1,) * (x.ndim - 1))
        return jnp.where(mask, x_new, x), ok


def sip(
    network_output,
    simulate,
    target,
    *,
    solver: AbstractInverseSolver | None = None,
    inverse=None,
    loss=None,
    eta: float = 1.0,
    proxy: AbstractProxy | None = None,
    precision: np.dtype | type | str = jnp.float32,
    warn_failures: float | None = 0.5,
) -> Estimator:
    """Scale-invariant physics: ``(params, batch) -> (∇_θ L_proxy, stats)``.

    Apply with the optimizer of your choice (the paper: Adam). ``stats`` holds ``loss``
    (the batch-mean ``loss(y, sample)`` if given, else the proxy), ``proxy`` and
    ``inverse_failures`` (samples whose local solve failed and got no update).

    Arguments:
        network_output: ``network_output(params, sample) -> x``, the network for one sample.
        simulate: ``simulate(x, sample) -> y``, the physics (needs derivatives in x only
            if the solver does).
        target: ``target(sample) -> y*``, the y-space target.
        solver: the local inverse (:mod:`physgrad.inverse`); default: ``Analytic(inverse)``
            if ``inverse`` is given, else ``GaussNewton()``.
        inverse: ``inverse(x, y, y_target, sample) -> x̃``, a closed-form local inverse.
        loss: ``loss(y, sample) -> L_i``, for reporting only.
        eta: η, the fraction of the y-space Newton step (1: all the way to y*).
        proxy: :class:`L2Proxy` (½‖x − x̃‖², the paper's; None: this) or :class:`L1Proxy` (Σ|x − x̃|).
        precision: ``jnp.float64`` runs the inverse solve in double precision (also inside
            your own ``jax.jit`` with x64 off: :func:`physgrad.precision.float64_call`).
        warn_failures: warn (:class:`physgrad.inverse.InverseFailureWarning`, once) when
            more than this fraction of a batch's solves fail; None: never.
    """
    objective = Objective(loss=loss, network_output=network_output, simulate=simulate, target=target, inverse=inverse)
    proxy = L2Proxy() if proxy is None else proxy
    return Estimator(ScaleInvariantPhysics(solver, eta, proxy, precision, warn_failures), objective)

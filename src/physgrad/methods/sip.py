"""Scale-invariant physics (SIP) updates: train the network on a local physics inverse.

Source: Holl, Koltun, Thuerey, *Scale-invariant Learning by Physics Inversion*, NeurIPS
2022 (arXiv 2109.15048 v3, §3 and Algorithm 1); PBDL book, chapter "Scale-invariant
physics training".

Per mini-batch, with the network output x_i = f(y*_i; θ) and y_i = P(x_i):

    y_t,i = y_i + η (y*_i − y_i)                  (the Newton step of an L2 loss in y)
    x̃_i  = stop_gradient(P⁻¹(y_t,i; x_i))        (local inverse solver, per sample)
    L_proxy = (1/b) Σ_i ½ ‖x_i − x̃_i‖²            (or (1/b) Σ_i Σ_j |x_ij − x̃_ij|, proxy="l1")
    d = ∇_θ L_proxy                                (applied by any optax optimizer; Adam in the paper)

The simulator and the solver run on stop-gradient values outside the network's autodiff:
no gradient flows into the simulator (it may be non-differentiable, e.g. an external code,
when the solver does not need derivatives), and the inverse may run in float64
(``precision="float64"``, scoped to the solve: the user's process keeps its settings).
A sample whose solve does not converge (or is not finite) gets x̃ = x, i.e. contributes
nothing, and is counted in the step's ``inverse_failures``. The authors sum the proxy over
the batch; physgrad averages (Adam is invariant to the factor; SGD's lr absorbs it). With
η = 1 and linear invertible P, x̃ = x* and SIP is supervised training (the paper's §3).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..inverse import AbstractInverseSolver, Analytic, GaussNewton
from ..precision import float64_scope, to_float64
from .base import AbstractRule, Estimator, Objective, required

PROXIES = ("l2", "l1")
PRECISIONS = ("float32", "float64")


class ScaleInvariantPhysics(AbstractRule):
    """``d = ∇_θ ½‖f(y*; θ) − x̃‖²`` with x̃ from a local physics inverse.

    ``solver=None`` picks the problem's analytic inverse when it has one, else
    :class:`~physgrad.inverse.GaussNewton`; ``Analytic()`` without a function uses the
    problem's inverse."""

    solver: AbstractInverseSolver | None = eqx.field(static=True, default=None)
    eta: float = eqx.field(static=True, default=1.0)
    proxy: str = eqx.field(static=True, default="l2")
    precision: str = eqx.field(static=True, default="float32")

    def __check_init__(self):
        if self.proxy not in PROXIES:
            raise ValueError(f"unknown proxy {self.proxy!r}; valid choices: {', '.join(PROXIES)}")
        if not self.eta > 0:
            raise ValueError(f"eta must be > 0 (the fraction of the y-space step), got {self.eta}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r}; valid choices: {', '.join(PRECISIONS)}")
        if self.solver is not None and not isinstance(self.solver, AbstractInverseSolver):
            raise ValueError(f"solver must be a physgrad.inverse solver object, got {self.solver!r}")

    def resolve_solver(self, objective) -> AbstractInverseSolver:
        """The solver with the problem's analytic inverse bound where it stands for it."""
        solver = self.solver
        if solver is None:
            solver = Analytic() if objective.inverse is not None else GaussNewton()
        if isinstance(solver, Analytic) and solver.fn is None:
            if objective.inverse is None:
                raise ValueError(
                    "this problem has no analytic inverse; valid choices: gauss_newton, saddle_free_newton, "
                    "lbfgs, linear_solve"
                )
            solver = Analytic(objective.inverse)
        return solver

    def check(self, objective):
        if objective.simulate is None or objective.network_output is None:
            raise ValueError("sip needs a problem that exposes network_output and simulate")
        if objective.target is None:
            raise ValueError("sip needs a problem with a y-space target (define target(sample))")
        self.resolve_solver(objective)

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
        if self.proxy == "l2":
            proxy, cotangent = 0.5 * jnp.sum(diff**2) / b, diff / b
        else:
            proxy, cotangent = jnp.sum(jnp.abs(diff)) / b, jnp.sign(diff) / b
        (grads,) = pullback(cotangent.astype(x.dtype))
        stats.setdefault("loss", proxy)
        return grads, {**stats, "proxy": proxy, "inverse_failures": jnp.sum(~ok)}

    def local_inverse(self, objective, x, y, batch):
        """(x̃, converged) per sample; failed samples get x̃ = x."""
        solver = self.resolve_solver(objective)
        float64 = self.precision == "float64"
        with float64_scope(float64):
            cast = to_float64 if float64 else (lambda a: a)
            y_, y_star = cast(y), cast(jax.vmap(objective.target)(batch))
            # (1 − η) y + η y*, not y + η (y* − y): exactly y* at η = 1 even when y* ≪ y.
            y_target = (1 - self.eta) * y_ + self.eta * y_star
            result = jax.vmap(lambda *a: solver(objective.simulate, *a))(
                cast(x), y_, y_target, jax.tree.map(cast, batch)
            )
            ok = result.converged & jnp.all(jnp.isfinite(result.x.reshape(x.shape[0], -1)), axis=1)
            x_new = result.x.astype(x.dtype)
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
    proxy: str = "l2",
    precision: str = "float32",
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
        proxy: ``"l2"`` (½‖x − x̃‖²) or ``"l1"``.
        precision: ``"float64"`` runs the inverse solve in double precision.
    """
    objective = Objective(loss=loss, network_output=network_output, simulate=simulate, target=target, inverse=inverse)
    return Estimator(ScaleInvariantPhysics(solver, eta, proxy, precision), objective)

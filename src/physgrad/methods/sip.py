"""Scale-invariant physics (SIP) updates: train the network on a local physics inverse.

Source: Holl, Koltun, Thuerey, *Scale-invariant Learning by Physics Inversion*, NeurIPS
2022 (arXiv 2109.15048 v3); PBDL book "SIP training"; sip.md §1.3, §7.

Per mini-batch, with the network output x_i = f(y*_i; θ) and y_i = P(x_i):

    y_t,i = y_i + η (y*_i − y_i)                  (the Newton step of an L2 loss in y)
    x̃_i  = stop_gradient(P⁻¹(y_t,i; x_i))        (local inverse solver, per sample)
    L_proxy = (1/b) Σ_i ½ ‖x_i − x̃_i‖²            (or (1/b) Σ_i Σ_j |x_ij − x̃_ij|, proxy="l1")
    θ ← θ + optimizer(∇_θ L_proxy)                 (Adam by default)

The simulator and the solver run on stop-gradient values outside the network's autodiff:
no gradient flows into the simulator (it may be non-differentiable, e.g. an external code,
when the solver does not need derivatives), and it may run in float64 (``precision``).
A sample whose solve does not converge (or is not finite) gets x̃ = x, i.e. contributes
nothing, and is counted in the step's ``inverse_failures`` (logged per evaluation window as
``step_inverse_failures`` and summed in ``summary.json``). The authors sum the proxy
over the batch; physgrad averages (Adam is invariant to the factor; SGD's lr absorbs it).
With η = 1 and linear invertible P, x̃ = x* and SIP is supervised training (sip.md §1.3).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

from ..inverse import AbstractInverseSolver, make_solver
from .base import AbstractMethod
from .dp import OPTIMIZERS

PROXIES = ("l2", "l1")
PRECISIONS = ("float32", "float64")


class ScaleInvariantPhysics(AbstractMethod):
    """``θ ← θ + optimizer(∇_θ ½‖f(y*; θ) − x̃‖²)`` with x̃ from a local physics inverse."""

    solver_name: str = eqx.field(static=True)
    solver_settings: tuple = eqx.field(static=True)
    eta: float = eqx.field(static=True)
    proxy: str = eqx.field(static=True)
    precision: str = eqx.field(static=True)
    optimizer: optax.GradientTransformation = eqx.field(static=True)

    def __check_init__(self):
        if self.proxy not in PROXIES:
            raise ValueError(f"unknown proxy {self.proxy!r}; valid choices: {', '.join(PROXIES)}")
        if not self.eta > 0:
            raise ValueError(f"eta must be > 0 (the fraction of the y-space step), got {self.eta}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r}; valid choices: {', '.join(PRECISIONS)}")
        make_solver(self.solver_name, analytic=_probe, **dict(self.solver_settings))

    def solver(self, objective) -> AbstractInverseSolver:
        return make_solver(self.solver_name, analytic=objective.inverse, **dict(self.solver_settings))

    def check(self, objective):
        if objective.simulate is None or objective.network_output is None:
            raise ValueError("sip needs a problem that exposes network_output and simulate")
        if objective.target is None:
            raise ValueError("sip needs a problem with a y-space target (define target(sample))")
        self.solver(objective)

    def init(self, params):
        return self.optimizer.init(params)

    def step(self, objective, params, state, batch):
        x, pullback = jax.vjp(lambda p: jax.vmap(objective.network_output, (None, 0))(p, batch), params)
        x0 = jax.lax.stop_gradient(x)
        y = jax.vmap(objective.simulate)(x0, batch)
        loss = jnp.mean(jax.vmap(objective.loss)(y, batch))
        x_tilde, ok = self.local_inverse(objective, x0, y, batch)
        b = x.shape[0]
        diff = x0 - x_tilde
        if self.proxy == "l2":
            proxy, cotangent = 0.5 * jnp.sum(diff**2) / b, diff / b
        else:
            proxy, cotangent = jnp.sum(jnp.abs(diff)) / b, jnp.sign(diff) / b
        (grads,) = pullback(cotangent.astype(x.dtype))
        updates, state = self.optimizer.update(grads, state, params)
        stats = {"loss": loss, "proxy": proxy, "inverse_failures": jnp.sum(~ok)}
        return optax.apply_updates(params, updates), state, stats

    def local_inverse(self, objective, x, y, batch):
        """(x̃, converged) per sample; failed samples get x̃ = x."""
        cast = _caster(self.precision)
        y, y_star = cast(y), cast(jax.vmap(objective.target)(batch))
        # (1 − η) y + η y*, not y + η (y* − y): exactly y* at η = 1 even when y* ≪ y.
        y_target = (1 - self.eta) * y + self.eta * y_star
        solver = self.solver(objective)
        result = jax.vmap(lambda *a: solver(objective.simulate, *a))(cast(x), y, y_target, jax.tree.map(cast, batch))
        ok = result.converged & jnp.all(jnp.isfinite(result.x.reshape(x.shape[0], -1)), axis=1)
        mask = ok.reshape((-1,) + (1,) * (x.ndim - 1))
        return jnp.where(mask, result.x.astype(x.dtype), x), ok


def _probe(*args):  # stands in for a problem's analytic inverse when checking settings
    raise NotImplementedError


def _caster(precision):
    def cast(a):
        if precision == "float64" and jnp.issubdtype(a.dtype, jnp.floating):
            return a.astype(jnp.float64)
        if precision == "float64" and jnp.issubdtype(a.dtype, jnp.complexfloating):
            return a.astype(jnp.complex128)
        return a

    return cast


def sip(
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
):
    """Scale-invariant physics: fit the network to a local inverse x̃ = P⁻¹(y + η(y* − y); x) (Holl et al. 2022)."""
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}; valid choices: {', '.join(OPTIMIZERS)}")
    settings = (("rcond", rcond), ("max_loss_change", max_loss_change), ("max_steps", max_steps), ("tol", tol), ("krylov", krylov))
    return ScaleInvariantPhysics(solver, settings, eta, proxy, precision, OPTIMIZERS[optimizer](lr))

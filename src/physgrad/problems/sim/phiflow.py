"""PhiFlow as a simulator source: PhiFlow functions of grids as pure JAX functions of arrays.

PhiFlow (Holl & Thuerey, ``phiflow`` on PyPI, with its tensor library ``phiml``) writes
simulations as functions of ``CenteredGrid`` / ``StaggeredGrid`` fields. This module turns
such a function into a per-sample function of plain JAX arrays, so it can be a physgrad
simulator (``simulate(x, sample)``) under ``jax.jit``, ``jax.vmap`` and ``jax.grad``:

- :func:`wrap` (:class:`PhiFlowFunction`): ``wrap(fn, Domain((n, n), dx), inputs=(Centered(),
  Staggered()), outputs=(Centered(), Staggered()))`` gives ``f(marker, velocity) ->
  (marker, velocity)`` on arrays. Array layouts are :mod:`physgrad.problems.sim.fluid`'s (PhiFlow's
  own, checked in the tests): axis 0 is x, axis 1 is y; a staggered velocity is ``(d, *n)``
  with component a on the *lower* a-faces of the cells (periodic grids only). The kinds and
  the domain's boundary (:class:`Periodic`, :class:`Zero`, :class:`ZeroGradient`) are objects
  (:mod:`physgrad.problems.sim.phiflow_fields`).
- :func:`step` and :func:`rollout`: the SIP paper's inviscid fluid step written with
  PhiFlow (``advect.mac_cormack``, ``fluid.make_incompressible`` with an explicit
  ``Solve('CG', 0, tol)`` warm started from the previous pressure, energy rescale, marker
  advection). :func:`rollout` has the signature, semantics and layout of
  :func:`physgrad.problems.sim.fluid.rollout` (``solver_tol`` in place of ``solver``), so a problem
  switches simulators with one setting.
- :func:`import_phiflow`: the lazy import. ``import physgrad`` and ``import
  physgrad.problems.sim.phiflow`` do not import PhiFlow; the first adapter call does (``pip install
  physgrad[phiflow]``), and then restores the process's configuration (below).

Limits:

- **Reverse mode only.** PhiML differentiates its linear solves by an implicit adjoint
  (``jax.custom_vjp``), so ``jax.jvp`` / ``jax.jacfwd`` / ``jax.hessian`` fail on any
  function that solves. Wrapped functions carry ``reverse_only = True``
  (:func:`physgrad.jacobian.is_reverse_only`); :class:`physgrad.inverse.GaussNewton` then
  builds its Jacobian by ``jacrev``, and the forward-mode pieces (``LinearSolve``,
  ``SaddleFreeNewton``, ``newton``) say so in one line when reverse-over-reverse fails.
- **Explicit solves.** PhiFlow's default ``Solve()`` on a periodic domain falls back to a
  host-side SciPy direct solver (no jit, no gradient on the device). A wrapped function
  that runs a solve with method ``'auto'`` or ``'scipy-*'`` raises a one-line
  ``ValueError`` (``explicit_solve=False`` lifts this); the shipped step always passes
  ``Solve('CG', 0, solver_tol)``.
- Tracing PhiFlow is slow (seconds per fluid step) and XLA is slow to compile its graphs
  (tens of seconds for a jitted gradient of the fluid on one CPU core, whatever the grid
  size). A wrapped function is traced once per (function, input shapes and dtypes) and
  replayed from a cached jaxpr afterwards, so ``fn`` must be pure and must not close over
  traced arrays (pass them as :class:`Plain` inputs); :func:`rollout` traces one step inside
  ``lax.scan``. ``dx``, ``dt`` and the grid size must be Python numbers.
- Precision follows the inputs: float64 arrays (x64 on) run PhiML at 64 bits, anything
  else at 32 bits.
- Not identical to :mod:`physgrad.problems.sim.fluid`: PhiFlow 3.4's ``advect.mac_cormack`` clamps each
  staggered velocity component to the 2 × 2 values around the back-traced point as if the
  component were cell centred (half a cell off along its own axis), fluid.py to the
  component's own faces. Everything else (marker advection, projection, energy rescale)
  agrees to float32 rounding; with that limiter written into the JAX fluid, states agree to
  ~3e-5 and gradients to ~2e-4 relative (``tests/test_phiflow.py``).

What importing PhiFlow changes, and what :func:`import_phiflow` does about it (PhiFlow
3.4 / PhiML 1.16):

- ``jax_enable_x64`` is switched **on** by PhiML's JAX backend at import: every JAX config
  flag the import changed is set back (only x64 changes in these versions);
- PhiML's global default backend becomes JAX (``phi.jax.flow``): set back to what it was
  (NumPy if PhiML was not imported before). Wrapped functions run inside a JAX backend
  context of their own, so nothing depends on the global default;
- PhiML's precision (32 bits) is not changed by the import; it is re-set if it were;
- not restored (documented): SciPy, imported by PhiFlow, adds its own two warnings filters
  at import (``always`` for ``scipy.special.SpecialFunctionWarning``, ``ignore`` for
  NumPy's "matrix subclass" ``PendingDeprecationWarning``) which SciPy relies on, exactly
  as if the user had imported SciPy; PhiML creates its own logger ``"Φ-ML"`` with a console
  handler (no change to the root logger or other loggers); the modules of PhiFlow, PhiML
  and SciPy stay imported. The root logger, NumPy's print/error settings and the
  environment are untouched.
- PhiML warns (``DeprecationWarning``, "symmetric-gradient extrapolation is experimental")
  about one of its own module constants at import: silenced during the import only.
- The flags are read and restored at their *global* values, so a first import inside
  ``jax.enable_x64(True)`` (SIP's float64 inverse) leaves x64 off outside the scope.
- PhiML's JAX backend re-enables x64 by itself if asked to compute at 64 bits with x64
  off; wrapped functions only ask for 64 bits when their inputs are already float64.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import importlib
import importlib.util
import threading
import warnings
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.extend.core as jax_core
import jax.numpy as jnp

from ...jacobian import mark_reverse_only
from .fluid import AbstractFluid, unroll
from .phiflow_fields import (
    BOUNDARIES,
    KINDS,
    AbstractBoundary,
    AbstractKind,
    Centered,
    Domain,
    Periodic,
    Plain,
    Staggered,
    Vector,
    Zero,
    ZeroGradient,
    kind_of,
)

INSTALL_HINT = "PhiFlow is not installed; install it with `pip install physgrad[phiflow]` (phiflow>=3.4, phiml>=1.16)"

_LOCK = threading.Lock()
_FLOW = None


# --- the lazy import ---------------------------------------------------------------------
def import_phiflow():
    """``phi.jax.flow``, imported on first use with the process's configuration restored.

    Raises ``ImportError`` naming ``pip install physgrad[phiflow]`` when PhiFlow is missing.
    See the module docstring for what the import changes and what is set back."""
    global _FLOW
    if _FLOW is not None:
        return _FLOW
    with _LOCK:
        if _FLOW is not None:
            return _FLOW
        config = _global_jax_config()
        try:
            with warnings.catch_warnings():  # PhiML's own, about one of its module constants
                warnings.filterwarnings("ignore", message="symmetric-gradient extrapolation is experimental")
                phiml_backend = importlib.import_module("phiml.backend")
                default_backend, precision = phiml_backend.default_backend(), phiml_backend.get_precision()
                flow = importlib.import_module("phi.jax.flow")
        except ImportError as error:
            _restore_jax_config(config)
            from ...extras import MissingExtra  # an ImportError and a ConfigError: one line from the CLI

            raise MissingExtra(f"{INSTALL_HINT} ({error})") from error
        except BaseException:
            _restore_jax_config(config)
            raise
        _restore_jax_config(config)
        if phiml_backend.default_backend() is not default_backend:
            phiml_backend.set_global_default_backend(default_backend)
        if phiml_backend.get_precision() != precision:
            phiml_backend.set_global_precision(precision)
        _FLOW = flow
        return flow


def _global_jax_config() -> dict:
    """JAX's flags as set globally: not the values of an enclosing scope such as
    ``jax.enable_x64(True)`` (the first import may well happen inside SIP's float64 scope)."""
    holders = getattr(jax.config, "_value_holders", {})
    values = dict(jax.config.values)
    for name, holder in holders.items():
        if hasattr(holder, "get_global"):
            values[name] = holder.get_global()
    return values


def _restore_jax_config(before: dict) -> None:
    after = _global_jax_config()
    for name, value in before.items():
        if after.get(name, value) != value:
            jax.config.update(name, value)


def phiflow_available() -> bool:
    """Whether PhiFlow can be imported (without importing it)."""
    return importlib.util.find_spec("phi") is not None and importlib.util.find_spec("phiml") is not None


# --- the adapter -----------------------------------------------------------------------------
class PhiFlowFunction(eqx.Module):
    """A PhiFlow function of fields as a pure per-sample JAX function of arrays.

    ``f(*arrays)`` converts each array by its ``inputs`` kind (:class:`Centered`, ...), calls
    ``fn(*fields)`` under PhiML's JAX backend at the inputs' precision, and converts the
    result(s) back by ``outputs`` (a kind: one array; a tuple of kinds: a tuple). Usable under
    ``jit``, ``vmap`` (vmap outside: the function sees one sample), ``grad``, ``jacrev``;
    **not** ``jvp``/``jacfwd`` when ``fn`` solves (``reverse_only``)."""

    fn: Callable = eqx.field(static=True)
    domain: Domain = eqx.field(static=True)
    inputs: tuple[AbstractKind, ...] = eqx.field(static=True)
    outputs: AbstractKind | tuple[AbstractKind, ...] = eqx.field(static=True)
    explicit_solve: bool = eqx.field(static=True, default=True)

    reverse_only: ClassVar[bool] = True  # read by physgrad.jacobian.is_reverse_only

    def __post_init__(self):
        # kinds as objects; a string (physgrad 0.1.0's spelling) becomes its object with a warning
        self.inputs = tuple(kind_of(k) for k in self.inputs)
        outputs: Any = self.outputs
        self.outputs = kind_of(outputs) if isinstance(outputs, (AbstractKind, str)) else tuple(map(kind_of, outputs))

    def __call__(self, *arrays):
        if len(arrays) != len(self.inputs):
            raise TypeError(f"this PhiFlow function takes {len(self.inputs)} arrays ({self.inputs}), got {len(arrays)}")
        import_phiflow()
        return _call(self, tuple(jnp.asarray(a) for a in arrays))

    def run(self, arrays: tuple):
        """The PhiFlow computation on JAX arrays, inside :func:`phiml_scope` (no custom_vjp
        boundary: differentiate :meth:`__call__` instead)."""
        flow = import_phiflow()
        with phiml_scope(arrays), _SolveRecorder() as solves:
            fields = [kind.to_field(flow, a, self.domain) for a, kind in zip(arrays, self.inputs)]
            result = self.fn(*fields)
            if isinstance(self.outputs, AbstractKind):
                out = self.outputs.from_field(flow, result, self.domain)
            else:
                if not isinstance(result, (tuple, list)) or len(result) != len(self.outputs):
                    raise ValueError(f"the PhiFlow function must return {len(self.outputs)} values ({self.outputs})")
                out = tuple(k.from_field(flow, r, self.domain) for k, r in zip(self.outputs, result))
        if self.explicit_solve:
            for requested, used in solves.methods:
                if requested == "auto" or requested.startswith("scipy-"):
                    raise ValueError(
                        f"a PhiFlow solve ran with method {requested!r} ({used}): PhiFlow's default Solve() is a host-side "
                        "SciPy solve on periodic domains; pass an explicit one, e.g. Solve('CG', 0, 1e-4, x0=guess)"
                    )
        return out


# PhiML's own custom_vjp rules (its implicit-adjoint solves) run their Python code whenever JAX
# gets to them: the backward pass, and re-traces by enclosing transforms (scan, checkpoint),
# long after the wrapped call returned. They read PhiML's global state (default backend,
# precision). One custom_vjp around the whole PhiFlow function keeps every one of those calls
# inside phiml_scope: its forward runs jax.vjp of the PhiFlow code in the scope, and its
# backward applies that pullback (a pytree of residual arrays) in the scope again.
#
# Tracing PhiFlow is slow (seconds per fluid step), and JAX re-traces a custom_vjp's primal and
# forward on every transform (scan under grad calls the forward twice). So the three pieces
# (primal, forward with residuals, backward) are traced once per function and input types into
# jaxprs and replayed (_replay): equal settings and shapes never trace PhiFlow twice.
@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _call(function: PhiFlowFunction, arrays: tuple):
    return _replay(("primal", function), function.run, arrays)


def _vjp(function, arrays):
    out, pullback = jax.vjp(function.run, arrays)
    return out, pullback


def _call_fwd(function, arrays):
    out, pullback = _replay(("forward", function), functools.partial(_vjp, function), arrays)
    return out, (pullback, arrays)


def _call_bwd(function, residuals, cotangent):
    pullback, arrays = residuals
    return _replay(("backward", function), lambda pb, ct: pb(ct), pullback, cotangent, scope=arrays)


_call.defvjp(_call_fwd, _call_bwd)

_JAXPRS: collections.OrderedDict = collections.OrderedDict()
_JAXPRS_SIZE = 64


def _replay(key, fn, *args, scope=None):
    """``fn(*args)``, traced (in :func:`phiml_scope`) once per ``key`` and argument types into a
    jaxpr that is evaluated from then on. ``fn`` must be pure; its output a pytree of arrays
    (and static parts, e.g. a pullback's function)."""
    flat, in_tree = jax.tree.flatten(args)
    cache_key = (key, in_tree, tuple(jax.typeof(a) for a in flat))
    entry = _JAXPRS.get(cache_key)
    if entry is None:
        with phiml_scope(args if scope is None else scope):
            closed, shapes = jax.make_jaxpr(fn, return_shape=True)(*args)
        entry = (closed, jax.tree.structure(shapes))
        _JAXPRS[cache_key] = entry
        while len(_JAXPRS) > _JAXPRS_SIZE:
            _JAXPRS.popitem(last=False)
    else:
        _JAXPRS.move_to_end(cache_key)
    closed, out_tree = entry
    with phiml_scope(args if scope is None else scope):
        out = jax_core.jaxpr_as_fun(closed)(*flat)
    return jax.tree.unflatten(out_tree, out)


def phiml_scope(arrays) -> contextlib.ExitStack:
    """PhiML's JAX backend and the precision of ``arrays`` (64 bits if any is float64, else
    32), as one context; nothing global is changed."""
    flow = import_phiflow()
    from phiml.backend.jax import JAX

    floats = [a.dtype for a in jax.tree.leaves(arrays) if jnp.issubdtype(a.dtype, jnp.floating)]
    bits = 64 if floats and jnp.result_type(*floats) == jnp.float64 else 32
    stack = contextlib.ExitStack()
    stack.enter_context(JAX)
    stack.enter_context(flow.math.precision(bits))
    return stack


def wrap(fn: Callable, domain: Domain, inputs, outputs, *, explicit_solve: bool = True) -> PhiFlowFunction:
    """``fn(*fields) -> field(s)`` (PhiFlow) as ``f(*arrays) -> array(s)`` (JAX, per sample).

    Arguments:
        fn: a PhiFlow function of fields (closures or ``functools.partial`` carry constants).
        domain: the :class:`Domain` every field lives on.
        inputs: one kind per argument: :class:`Centered` (array ``(*n)``), :class:`Staggered`
            (``(d, *n)``, lower faces, periodic), :class:`Vector` (centred vector ``(d, *n)``)
            or :class:`Plain` (any JAX array, passed to ``fn`` as it is).
        outputs: a kind (one array returned) or a sequence of kinds (a tuple returned).
        explicit_solve: raise ``ValueError`` when ``fn`` runs a PhiFlow solve with the default
            method (``'auto'``) or a host-side ``'scipy-*'`` one.
    """
    outputs = kind_of(outputs) if isinstance(outputs, (AbstractKind, str)) else tuple(outputs)
    return PhiFlowFunction(fn, domain, tuple(inputs), outputs, explicit_solve)


def _solve_recorder_base():
    return importlib.import_module("phiml.math._optimize").SolveTape


class _SolveRecorder:
    """Records the method of every PhiML linear solve run (or traced) in its scope.

    A :class:`phiml.math.SolveTape` that keeps only ``(requested method, used method)``
    (no duplicate-solve warnings, no trajectories)."""

    def __init__(self):
        tape_class = _solve_recorder_base()
        recorder = self

        class Tape(tape_class):
            def _add(self, solve, trj, result):  # noqa: ARG002  (PhiML's hook)
                recorder.methods.append((str(solve.method), str(getattr(result, "method", "?"))))

        self.methods: list[tuple[str, str]] = []
        self._tape = Tape()

    def __enter__(self):
        self._tape.__enter__()
        return self

    def __exit__(self, *exc):
        return self._tape.__exit__(*exc)


# --- the SIP fluid step with PhiFlow ------------------------------------------------------------
def step_fields(marker, velocity, pressure, dt: float, solver_tol: float = 1e-4):
    """The authors' step on PhiFlow fields: ``(marker, velocity, pressure) -> same``.

    Silences two warnings PhiFlow 3.4 raises from its own code on every trace: the
    "Rank deficiency >= 1" of the (singular, periodic) pressure Laplacian, which PhiFlow
    handles itself, and the deprecation of ``Field.closest_values`` that ``mac_cormack`` calls."""
    flow = import_phiflow()
    math, field = flow.math, flow.field
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Rank deficiency >= 1 detected", category=RuntimeWarning)
        warnings.filterwarnings(
            "ignore", message=r"Field.closest_values\(\) is deprecated", category=DeprecationWarning
        )
        e0 = field.mean(velocity**2)
        velocity = flow.advect.mac_cormack(velocity, velocity, dt)
        solve = flow.Solve("CG", 0, solver_tol, x0=pressure)
        velocity, pressure = flow.fluid.make_incompressible(velocity, solve=solve)
        e = field.mean(velocity**2)
        safe = math.where(e > 0, e, 1.0)  # the authors' where(e == 0, e, sqrt(e0 / e)), NaN-free gradient
        velocity = velocity * math.where(e > 0, math.sqrt(e0 / safe), 0.0)
        marker = flow.advect.mac_cormack(marker, velocity, dt)
    return marker, velocity, pressure


def step_function(n: int, dt: float, dx: float, solver_tol: float = 1e-4) -> PhiFlowFunction:
    """:func:`step_fields` on an ``n × n`` periodic grid as ``f(marker, velocity, pressure)``."""
    return wrap(
        _Step(float(dt), float(solver_tol)),
        Domain((n, n), float(dx)),
        inputs=(Centered(), Staggered(), Centered()),
        outputs=(Centered(), Staggered(), Centered()),
    )


class _Step(eqx.Module):  # hashable: equal settings give equal (static) PhiFlowFunctions
    dt: float = eqx.field(static=True)
    solver_tol: float = eqx.field(static=True)

    def __call__(self, marker, velocity, pressure):
        return step_fields(marker, velocity, pressure, self.dt, self.solver_tol)


def step(marker, velocity, pressure, dt: float, dx: float, solver_tol: float = 1e-4):
    """One step on arrays, as :func:`physgrad.problems.sim.fluid.step`: ``(marker, velocity, pressure) -> same``."""
    return step_function(marker.shape[0], dt, dx, solver_tol)(marker, velocity, pressure)


def rollout(marker, velocity, steps: int, dt: float, dx: float, solver_tol: float = 1e-4):
    """:func:`physgrad.problems.sim.fluid.rollout` with PhiFlow: ``steps`` steps from a divergence-free
    staggered velocity ``(2, n, n)`` and a cell-centred marker ``(n, n)``, pressure guess 0.

    Returns the final ``(marker, velocity)`` and the markers after every step
    ``(steps, n, n)``. Reverse mode only (see the module docstring)."""
    return unroll(step_function(marker.shape[0], dt, dx, solver_tol), marker, velocity, jnp.zeros_like(marker), steps)


mark_reverse_only(rollout)
mark_reverse_only(step)


class PhiFlowFluid(AbstractFluid):
    """PhiFlow's own step as a fluid for :class:`physgrad.problems.NavierStokes`'s
    ``simulator``: :func:`rollout`, with PhiFlow's CG and its limiter (so the ``solver`` and
    ``limiter`` passed are PhiFlow's whatever they are). Reverse mode only."""

    def rollout(self, marker, velocity, steps, dt, dx, solver, limiter):
        return rollout(marker, velocity, steps, dt, dx)


__all__ = [
    "BOUNDARIES",
    "KINDS",
    "AbstractBoundary",
    "AbstractKind",
    "Centered",
    "Domain",
    "Periodic",
    "Plain",
    "Staggered",
    "Vector",
    "Zero",
    "ZeroGradient",
    "PhiFlowFluid",
    "PhiFlowFunction",
    "import_phiflow",
    "phiflow_available",
    "rollout",
    "step",
    "step_fields",
    "step_function",
    "wrap",
]

"""Per-sample Jacobians of the simulator output, stacked sample-major; and the helpers
that let Jacobian- and Hessian-based pieces handle reverse-mode-only simulators
(:func:`is_reverse_only`, :func:`supports_forward_mode`, :func:`dense_jacobian`,
:func:`dense_hessian`); the Jacobian mode objects :class:`ForwardMode`, :class:`ReverseMode`
and :class:`AutoMode` (how a dense Jacobian is built)."""

from __future__ import annotations

import abc
import functools
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.extend.core as jax_core
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree

from .errors import warn_deprecated


def flat_output(y: Array) -> Array:
    """One sample's output as a real vector; complex values become (Re, Im) pairs."""
    if jnp.iscomplexobj(y):
        y = jnp.stack([y.real, y.imag], axis=-1)
    return jnp.ravel(y)


def stacked_jacobian(predict: Callable[[PyTree, PyTree], Array], params: PyTree, batch: PyTree) -> tuple[Array, Array]:
    """The joint Jacobian ∂y/∂θ of all samples, rows sample-major, and the outputs.

    ``J[i·d + k, j] = ∂ y_i[k] / ∂ θ_j`` where ``d`` is the (flattened) output size, ``i``
    the sample and ``θ`` all parameters raveled in ``jax.flatten_util.ravel_pytree``
    order (one matrix over every layer: no per-layer treatment, as the paper).

    Computed by ``vmap(jacrev)`` over the batch: reverse mode because d < P, one
    forward pass per sample (the outputs come back as auxiliary data).

    Returns:
        ``(J, y)`` with ``J`` of shape (b·d, P) and ``y`` of shape (b, d).
    """
    flat, unravel = ravel_pytree(params)

    def per_sample(theta, sample):
        y = flat_output(predict(unravel(theta), sample))
        return y, y

    jac, y = jax.vmap(jax.jacrev(per_sample, has_aux=True), in_axes=(None, 0))(flat, batch)
    return jac.reshape(-1, flat.size), y


# --- simulators without forward mode -------------------------------------------------------
# A function built on ``jax.custom_vjp`` (e.g. PhiFlow/PhiML's implicit-adjoint linear solves,
# :mod:`physgrad.problems.sim.phiflow`) has reverse-mode derivatives only: ``jax.jvp``/``jacfwd`` raise
# "can't apply forward-mode autodiff (jvp) to a custom_vjp function" (while tracing, or only
# when the traced computation is evaluated or lowered). The helpers below let
# the Jacobian-based pieces pick reverse mode for such functions, and let the pieces that
# need forward mode say so in one line instead of JAX's internal error.

REVERSE_ONLY_ATTRIBUTE = "reverse_only"
MODES = ("auto", "forward", "reverse")  # the deprecated string spellings of the mode objects


def mark_reverse_only(fn: Callable) -> Callable:
    """``fn`` marked as reverse-mode only (``fn.reverse_only = True``; a wrapper if ``fn``
    takes no attributes). :func:`is_reverse_only` reads the mark."""
    try:
        setattr(fn, REVERSE_ONLY_ATTRIBUTE, True)
        return fn
    except (AttributeError, TypeError):

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            return fn(*args, **kwargs)

        wrapper.reverse_only = True  # type: ignore[attr-defined]
        return wrapper


def is_reverse_only(fn) -> bool:
    """Whether ``fn`` (or the function it wraps: ``functools.partial``/``eqx.Partial``'s
    ``func``, ``functools.wraps``' ``__wrapped__``) is marked reverse-mode only. A mark
    is a hint only: a closure around a marked function is found by :func:`supports_forward_mode`."""
    seen = set()
    while fn is not None and id(fn) not in seen:
        seen.add(id(fn))
        if getattr(fn, REVERSE_ONLY_ATTRIBUTE, False) is True:
            return True
        fn = getattr(fn, "func", None) or getattr(fn, "__wrapped__", None)
    return False


def is_forward_mode_error(error: BaseException) -> bool:
    """Whether ``error`` is JAX's refusal to apply forward mode to a ``custom_vjp``."""
    message = str(error)
    return isinstance(error, TypeError) and "forward-mode" in message and "custom_vjp" in message


def supports_forward_mode(fn: Callable, *primals, transform: Callable | None = None, source=None) -> bool:
    """Whether ``fn`` can be differentiated in forward mode at ``primals`` (trace time only).

    False for a function marked reverse-only (``fn``, or ``source``: the user's function that
    ``fn`` is built from); otherwise the answer of an abstract probe: ``transform(fn)``
    (default: a JVP) is traced to a jaxpr, and no means either JAX's custom_vjp error during
    tracing (e.g. under vmap) or a ``custom_lin`` equation left in the jaxpr (a custom_vjp's
    tangent, which JAX only refuses when it is evaluated or lowered). Works on tracers (inside
    jit/vmap); costs one extra trace of ``fn``, no computation."""
    if is_reverse_only(fn) or (source is not None and is_reverse_only(source)):
        return False
    if transform is None:
        probe = lambda *p: jax.jvp(fn, p, tangents_for(p))  # noqa: E731
    else:
        probe = transform(fn)
    try:
        closed = jax.make_jaxpr(probe)(*primals)
    except TypeError as error:
        if is_forward_mode_error(error):
            return False
        raise
    return not _uses_primitive(closed.jaxpr, "custom_lin")


def tangents_for(primals):
    """Tangents that ``jax.jvp`` accepts for ``primals``: each inexact leaf its own value, each
    integer or boolean leaf (a sample's solver index, a step counter) :func:`float0_zeros`."""
    return jax.tree.map(lambda x: x if has_tangent(x) else float0_zeros(x), primals)


def has_tangent(x) -> bool:
    """Whether JAX differentiates the leaf ``x``: floating or complex. An integer or boolean
    leaf's tangent and cotangent are zeros of dtype float0 (:func:`float0_zeros`)."""
    return bool(jnp.issubdtype(jnp.result_type(x), jnp.inexact))


def float0_zeros(x):
    """The only tangent or cotangent JAX takes for an integer or boolean leaf ``x``."""
    return np.zeros(np.shape(x), jax.dtypes.float0)


def _uses_primitive(jaxpr, name: str) -> bool:
    """Whether ``jaxpr`` or any jaxpr nested in its equations (jit, scan, cond, ...) binds ``name``."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == name:
            return True
        for sub in _jaxprs_in_params(eqn.params):
            if _uses_primitive(sub, name):
                return True
    return False


def _jaxprs_in_params(params):
    """The jaxprs among an equation's parameters (``jax.extend.core.jaxprs_in_params`` of
    JAX >= 0.10, written out: the same walk works on every supported JAX)."""
    for value in params.values():
        for v in value if isinstance(value, tuple) else (value,):
            if isinstance(v, jax_core.Jaxpr):
                yield v
            elif isinstance(v, jax_core.ClosedJaxpr):
                yield v.jaxpr


def forward_mode_error(what: str, alternative: str) -> ValueError:
    """The one-line error of a piece that needs forward mode, met with a reverse-only function."""
    return ValueError(
        f"{what} needs forward-mode derivatives (jax.jvp), which this simulator does not have "
        f"(reverse-mode only: a jax.custom_vjp such as PhiFlow's linear solves); {alternative}"
    )


def require_forward_mode(fn: Callable, *primals, what: str, alternative: str, source=None) -> None:
    """Raise :func:`forward_mode_error` unless ``fn`` supports forward mode at ``primals``."""
    if not supports_forward_mode(fn, *primals, source=source):
        raise forward_mode_error(what, alternative) from None


class AbstractJacobianMode(eqx.Module):
    """How the dense Jacobian ∂fn/∂x (output_size × x.size) of a flat-vector map is built:
    by ``x.size`` JVPs (forward mode) or ``output_size`` VJPs (reverse mode)."""

    name: ClassVar[str]

    @abc.abstractmethod
    def resolve(self, fn: Callable, x: Array, output_size: int, *, source=None) -> ForwardMode | ReverseMode:
        """The concrete mode used for ``fn`` at ``x`` (trace time)."""

    @abc.abstractmethod
    def jacobian(self, fn: Callable, x: Array, output_size: int, *, source=None, what: str) -> Array:
        """``∂fn/∂x``; ``what`` names the caller in a one-line error."""


class ForwardMode(AbstractJacobianMode):
    """Forward mode (``jax.jacfwd``); on a reverse-only ``fn`` a one-line ``ValueError``."""

    name: ClassVar[str] = "forward"

    def resolve(self, fn, x, output_size, *, source=None):
        return self

    def jacobian(self, fn, x, output_size, *, source=None, what):
        require_forward_mode(fn, x, what=what, alternative="use jacobian='reverse' or 'auto'", source=source)
        return jax.jacfwd(fn)(x)


class ReverseMode(AbstractJacobianMode):
    """Reverse mode (``jax.jacrev``): any differentiable ``fn``, PhiFlow's solves included."""

    name: ClassVar[str] = "reverse"

    def resolve(self, fn, x, output_size, *, source=None):
        return self

    def jacobian(self, fn, x, output_size, *, source=None, what):
        return jax.jacrev(fn)(x)


class AutoMode(AbstractJacobianMode):
    """Reverse mode when ``fn`` has no forward mode (:func:`supports_forward_mode`, probed at
    trace time) or when ``output_size < x.size`` (fewer VJPs than JVPs), else forward."""

    name: ClassVar[str] = "auto"

    def resolve(self, fn, x, output_size, *, source=None):
        if output_size < x.size or not supports_forward_mode(fn, x, source=source):
            return ReverseMode()
        return ForwardMode()

    def jacobian(self, fn, x, output_size, *, source=None, what):
        # the probe above has run: a forward choice needs no second check
        chosen = self.resolve(fn, x, output_size, source=source)
        return (jax.jacrev if isinstance(chosen, ReverseMode) else jax.jacfwd)(fn)(x)


_AUTO = AutoMode()
_MODE_NAMES = {"auto": AutoMode, "forward": ForwardMode, "reverse": ReverseMode}


def as_jacobian_mode(mode: AbstractJacobianMode | str) -> AbstractJacobianMode:
    """``mode``, or the object of a deprecated mode name (``"auto"|"forward"|"reverse"``,
    with a ``DeprecationWarning``)."""
    if isinstance(mode, AbstractJacobianMode):
        return mode
    if mode not in _MODE_NAMES:
        raise ValueError(f"unknown jacobian mode {mode!r}; valid choices: {', '.join(MODES)}")
    warn_deprecated(f"jacobian={mode!r} is deprecated; pass physgrad.jacobian.{_MODE_NAMES[mode].__name__}()")
    return _MODE_NAMES[mode]()


def jacobian_mode(
    fn: Callable, x: Array, output_size: int, mode: AbstractJacobianMode | str = _AUTO, *, source=None
) -> str:
    """``"forward"`` or ``"reverse"``: the mode ``mode`` uses for the dense Jacobian of ``fn``
    at the flat ``x`` (:class:`AutoMode`'s rule by default)."""
    return as_jacobian_mode(mode).resolve(fn, x, output_size, source=source).name


def dense_jacobian(
    fn: Callable,
    x: Array,
    output_size: int,
    mode: AbstractJacobianMode | str = _AUTO,
    *,
    source=None,
    what: str = "jacobian='forward'",
):
    """``∂fn/∂x`` (output_size × x.size) of a flat-vector map, built by ``mode``.

    An explicit :class:`ForwardMode` on a reverse-only ``fn`` raises a one-line ``ValueError``."""
    return as_jacobian_mode(mode).jacobian(fn, x, output_size, source=source, what=what)


def dense_hessian(fn: Callable, x: Array, *, what: str, alternative: str, source=None) -> Array:
    """The Hessian of a scalar ``fn`` at the flat ``x``: ``jax.hessian`` (forward over
    reverse), or reverse over reverse where forward mode fails (a custom_vjp whose backward
    pass is not forward-differentiable, e.g. PhiML's adjoint solve). When both fail, a
    one-line ``ValueError`` naming ``alternative``."""
    try:
        forward_over_reverse = supports_forward_mode(fn, x, transform=jax.hessian, source=source)
    except Exception:  # noqa: BLE001  (any other failure of jax.hessian: try reverse over reverse)
        forward_over_reverse = False
    if forward_over_reverse:
        return jax.hessian(fn)(x)
    try:
        return jax.jacrev(jax.jacrev(fn))(x)
    except Exception as error:  # noqa: BLE001  (any failure of the fallback: report it in one line)
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ValueError(
            f"{what} needs a Hessian; forward-over-reverse fails on this reverse-mode-only simulator and "
            f"reverse-over-reverse failed too ({type(error).__name__}: {first[:200]}); {alternative}"
        ) from None

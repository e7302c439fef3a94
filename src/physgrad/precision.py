"""Float64 where it is needed, without touching the user's JAX configuration.

Importing physgrad leaves ``jax_enable_x64`` as the user set it (off by default: a user's
``jnp.zeros`` stays float32). The few computations that need double precision scope it
with JAX's context manager ``jax.enable_x64(True)``:

* the Gram routes of the half-inverse (:mod:`physgrad.half_inverse`,
  :mod:`physgrad.half_inverse_large`): the Gram matrix squares the condition number, so it
  is formed and decomposed in float64 and the direction is cast back to the Jacobian's dtype;
* inverse solvers that iterate in float64 (:class:`physgrad.inverse.lbfgs.LBFGS`) and
  SIP's ``precision="float64"``;
* the float64 reference solvers that generate data (KS, Kolmogorov, advection), whose
  output is cast to float32 as before;
* problems whose own arrays are float64 (``AbstractProblem.needs_float64``): the engine
  runs their whole training inside the scope.

A scope inside a jitted function only changes how the ops within it are traced (float64
ops appear in the jaxpr even when x64 is off outside). Differentiating *through* a scoped
region does not work when the transpose runs outside the scope (the cotangents are then
traced in float32 against float64 primals), so only regions that are not differentiated
are scoped: their inputs pass through ``jax.lax.stop_gradient`` first (the half-inverse
direction and SIP's inverse-solver target are not differentiated by any update rule).

Usage::

    with float64_scope():
        x64 = to_float64(x)
        y = solve(x64)
        y = cast_like(y, x)   # back to x's dtypes before leaving the scope
"""

from __future__ import annotations

import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp

WIDE = {jnp.dtype(jnp.float16): jnp.float64, jnp.dtype(jnp.bfloat16): jnp.float64,
        jnp.dtype(jnp.float32): jnp.float64, jnp.dtype(jnp.complex64): jnp.complex128}  # fmt: skip


def x64_enabled() -> bool:
    """Whether 64-bit types are enabled here (globally or by an enclosing scope)."""
    return bool(jax.config.jax_enable_x64)  # pyright: ignore[reportAttributeAccessIssue]  # flags are set at run time


def float64_scope(enabled: bool = True) -> contextlib.AbstractContextManager:
    """``jax.enable_x64(True)`` if ``enabled``, else a no-op context (for a setting such as
    SIP's ``precision``: ``with float64_scope(precision == "float64"): ...``).

    Harmless where x64 is already on; on exit the previous setting is restored."""
    return jax.enable_x64(True) if enabled else contextlib.nullcontext()


def to_float64(tree):
    """Floating arrays of a pytree widened to float64 (complex to complex128); other
    leaves unchanged. Call it inside :func:`float64_scope`: outside, JAX would silently
    keep float32, so this raises instead."""
    if not x64_enabled():
        raise RuntimeError("to_float64 needs 64-bit types: call it inside physgrad.precision.float64_scope()")

    def widen(a):
        if eqx.is_array(a) and a.dtype in WIDE:
            return a.astype(WIDE[a.dtype])
        return a

    return jax.tree.map(widen, tree)


def cast_like(tree, like):
    """Each array of ``tree`` cast to the dtype of the matching leaf of ``like`` (same
    structure): the way back from a float64 computation to the caller's dtypes."""
    return jax.tree.map(lambda a, b: a.astype(b.dtype) if eqx.is_array(a) else a, tree, like)


def require_float64(what: str) -> None:
    """Raise one clear ``ValueError`` where float64 arrays are about to be built while
    64-bit types are off (JAX would silently make them float32)."""
    if not x64_enabled():
        raise ValueError(
            f"{what} computes in float64: run it inside `with jax.enable_x64(True):` or enable jax_enable_x64"
        )

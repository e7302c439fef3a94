"""Float64 where it is needed, without touching the user's JAX configuration.

Importing physgrad leaves ``jax_enable_x64`` as the user set it (off by default: a user's
``jnp.zeros`` stays float32). The few computations that need double precision scope it
with JAX's context manager ``jax.enable_x64(True)``:

* the Gram routes of the half-inverse (:mod:`physgrad.routes`: gram, structured,
  blockgram, lanczos): the Gram matrix squares the condition number, so it
  is formed and decomposed in float64 and the direction is cast back to the Jacobian's dtype;
* inverse solvers that iterate in float64 (:class:`physgrad.inverse.lbfgs.LBFGS`) and
  SIP's ``precision=jnp.float64``;
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

A scope covers what is traced inside it, not what JAX does with the trace later. Under a
``jax.jit`` the jaxpr is lowered to XLA only after the scope has closed, and primitives
whose lowering traces Python again (``mlir.lower_fun``: lineax's ``linear_solve``,
equinox's loop buffers and ``unvmap_max``, used by the Krylov and optimistix solvers) are
then traced with 64-bit types off against float64 operands: dtype errors and "float64
not available" warnings. :func:`float64_call` closes that gap for such computations: its
function is traced, batched *and lowered* with 64-bit types on.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.extend.core as jex
import jax.numpy as jnp
from jax.interpreters import batching, mlir

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


# --- a region traced, batched and lowered in float64 ------------------------------------
# One primitive whose parameter ``fun`` maps flat operands to flat results. ``fun`` is a
# jaxpr traced inside the scope (its closed-over tracers hoisted into the operands), so
# nothing of the caller's trace leaks into a parameter; every later stage that traces
# Python again (eager evaluation, vmap, lowering) runs it under ``jax.enable_x64(True)``.
float64_call_p = jex.Primitive("physgrad_float64_call")
float64_call_p.multiple_results = True


def _float64_impl(*operands, fun, out_avals):
    with jax.enable_x64(True):
        return fun(*operands)


def _float64_abstract_eval(*operands, fun, out_avals):
    return out_avals


def _float64_lowering(ctx, *operands, fun, out_avals):
    with jax.enable_x64(True):
        return mlir.lower_fun(fun, multiple_results=True)(ctx, *operands)


def _float64_batch(operands, dims, *, fun, out_avals):
    with jax.enable_x64(True):
        return _bind_float64(jax.vmap(fun, in_axes=tuple(dims)), operands), (0,) * len(out_avals)


def _bind_float64(fun: Callable, operands) -> list:
    """``fun(*operands)`` (flat arrays in, a flat list out) as one float64 region; call in
    a float64 scope."""
    closed = jax.make_jaxpr(fun)(*operands)
    consts = list(closed.consts)
    # The constants (closed-over tracers of the caller's trace among them) become leading
    # operands: a primitive's parameters must hold no tracer.
    jaxpr = closed.jaxpr.replace(constvars=[], invars=[*closed.jaxpr.constvars, *closed.jaxpr.invars])

    def flat(*all_operands):
        return jex.jaxpr_as_fun(jex.ClosedJaxpr(jaxpr, []))(*all_operands)

    return float64_call_p.bind(*consts, *operands, fun=flat, out_avals=tuple(closed.out_avals))


float64_call_p.def_impl(_float64_impl)
float64_call_p.def_abstract_eval(_float64_abstract_eval)
mlir.register_lowering(float64_call_p, _float64_lowering)
batching.primitive_batchers[float64_call_p] = _float64_batch


def float64_call(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` with 64-bit types on wherever JAX traces it: now, under ``vmap``, and
    when an enclosing ``jax.jit`` is lowered (which :func:`float64_scope` alone does not
    cover, module docstring). Works whether or not the user enabled ``jax_enable_x64``
    and leaves that setting alone.

    ``args`` and the results are pytrees of arrays; cast the results back to the caller's
    dtypes inside ``fn`` (no float64 array should leave it when x64 is off). Not
    differentiable (no JVP rule): pass constants (``stop_gradient``), as for a scope."""
    leaves, treedef = jax.tree.flatten(args)
    out_tree = []

    def flat(*flat_args):
        out = fn(*jax.tree.unflatten(treedef, flat_args))
        out_leaves, structure = jax.tree.flatten(out)
        out_tree[:] = [structure]
        return out_leaves

    with jax.enable_x64(True):
        leaves = [jnp.asarray(a) for a in leaves]
        out = _bind_float64(flat, leaves)
    return jax.tree.unflatten(out_tree[0], out)

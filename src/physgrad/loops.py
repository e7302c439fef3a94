"""``lax.scan`` as physgrad's rollouts call it: unrolled where XLA's CPU backend would run a
convolution inside a loop body.

XLA's CPU backend runs a convolution inside a ``while`` loop body 5–70× slower than the
same convolution outside one (jax-ml/jax issue 12868, still so in jax 0.10.2; measurements
in ``physgrad.engine.step.loop_chunk`` and docs/performance.md). A rollout of a
convolutional time-stepper is a ``lax.scan`` over a few steps, so on a CPU it paid that
slowdown on every step: a KS ONE step 108 ms scanned against 35 ms unrolled, a Kolmogorov
16² WIG step 272 against 40 ms. :func:`scan` unrolls such a scan fully when it is short
(at most :data:`MAX_UNROLL` steps), and leaves every other scan as it is (an unrolled loop
compiles longer and gains nothing without a convolution)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import jax

# The longest scan unrolled (steps): a training rollout (m ≤ 32 in the papers) or a test
# rollout of a few dozen steps; a data-generation run of hundreds of frames stays a loop.
MAX_UNROLL = 64


def scan(f: Callable, init: Any, xs: Any = None, length: int | None = None, reverse: bool = False):
    """``jax.lax.scan(f, init, xs, length, reverse)``, fully unrolled where :func:`unrolls`
    says so. Same arguments and results as ``lax.scan``."""
    return jax.lax.scan(f, init, xs, length=length, reverse=reverse, unroll=unrolls(f, init, xs, length))


def unrolls(f: Callable, init: Any, xs: Any = None, length: int | None = None, backend: str | None = None) -> bool:
    """Whether a scan of ``f`` is unrolled: on a CPU backend, at most :data:`MAX_UNROLL`
    steps, and ``f`` (traced once on the first step's shapes) holds a convolution."""
    if (backend or jax.default_backend()) != "cpu" or jax.config.jax_disable_jit:  # pyright: ignore[reportAttributeAccessIssue]
        return False  # under disable_jit the scan runs eagerly, and an abstract trace of f may fail
    leaves = jax.tree.leaves(xs)
    steps = length if length is not None else (leaves[0].shape[0] if leaves else None)
    if steps is None or steps > MAX_UNROLL or steps < 2:
        return False  # (no length at all: lax.scan says so in its own words)
    x0 = None if xs is None else jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), xs)
    jaxpr = jax.make_jaxpr(f)(init, x0)
    return any(name == "conv_general_dilated" for name in primitives(jaxpr.jaxpr))


def primitives(jaxpr) -> Iterator[str]:
    """The names of every primitive in ``jaxpr`` and in the jaxprs nested in its equations
    (``pjit``, ``custom_vjp``, ``cond``, ``scan``, ``checkpoint`` bodies)."""
    for eqn in jaxpr.eqns:
        yield eqn.primitive.name
        for value in eqn.params.values():
            for sub in value if isinstance(value, tuple | list) else (value,):
                inner = getattr(sub, "jaxpr", sub)  # a ClosedJaxpr holds its Jaxpr
                if hasattr(inner, "eqns"):
                    yield from primitives(inner)

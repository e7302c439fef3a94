"""The κ-power pseudo-inverse of a Jacobian applied to an output-space gradient.

Source: Schnell, Holl, Thuerey, *Half-Inverse Gradients for Physical Deep Learning*,
ICLR 2022, eq. for Δθ_HIG; the authors' ``gpinv``; PBDL book, chapter "Half-inverse
gradients".

For a Jacobian ``J`` (m × P) with thin SVD ``J = U Σ Vᵀ`` and a gradient ``g`` (m,),

    J^κ g := V Σ^κ Uᵀ g,

keeping only singular values ``σ > truncation · σ_max`` (strict) and *dropping* the
others (not clamping them). κ = +1 gives ``Jᵀ g`` (gradient descent), κ = −1 the
Gauss–Newton / pseudo-inverse step, κ = −½ the half-inverse gradient. In place of the
number κ every function here also takes a :class:`Damped` filter, ``σ ↦ σ / (σ² + λ)``,
which gives the Levenberg–Marquardt direction ``Jᵀ (J Jᵀ + λ I)⁻¹ g`` by the same routes.

Two exact routes compute the same vector:

* ``"svd"``: thin SVD of ``J`` in its own dtype (as the paper, float32);
* ``"gram"``: eigendecomposition of the smaller Gram matrix in float64. For a wide ``J``
  (m ≤ P), ``J Jᵀ = U Σ² Uᵀ`` and ``J^κ g = Jᵀ U Σ^{κ−1} Uᵀ g``; for a tall ``J``,
  ``Jᵀ J = V Σ² Vᵀ`` and ``J^κ g = V Σ^{κ−1} Vᵀ Jᵀ g``. The Gram matrix squares the
  condition number, which is why it is formed and decomposed in float64. This never
  forms the large factor (``V`` for wide, ``U`` for tall) and costs one matrix product
  of O(min(m,P)² · max(m,P)) plus an O(min(m,P)³) ``eigh``.

The float64 of the Gram route is scoped (:func:`physgrad.precision.float64_scope`): it
works whether or not the user enabled ``jax_enable_x64`` and leaves that setting alone.
A scoped region cannot be differentiated (its transpose would run outside the scope), so
the Gram route treats its inputs as constants (``stop_gradient``): the direction is an
update, never differentiated by an update rule. The SVD route stays differentiable.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .precision import float64_scope, to_float64

Route = Literal["auto", "svd", "gram"]
ROUTES = ("auto", "svd", "gram")


def choose_route(shape: tuple[int, int]) -> Literal["svd", "gram"]:
    """The cheaper exact route for a Jacobian of this shape.

    The Gram route wins whenever one side is clearly smaller than the other (every
    physgrad problem: rows = batch × output size ≪ parameters), because a matrix product
    and a small symmetric eigensolve are far cheaper than a bidiagonalisation. For
    nearly square matrices the SVD avoids squaring the condition number at no extra cost.
    Measured in ``benchmarks/hig_step.py``.
    """
    m, p = shape
    return "gram" if max(m, p) >= 2 * min(m, p) else "svd"


class Damped(eqx.Module):
    """The Levenberg–Marquardt filter ``f(σ) = σ / (σ² + λ)`` in place of ``σ^κ``.

    ``V f(Σ) Uᵀ g = Jᵀ (J Jᵀ + λ I)⁻¹ g = (Jᵀ J + λ I)⁻¹ Jᵀ g`` (Levenberg 1944,
    Marquardt 1963). λ → 0 gives the Gauss–Newton filter σ⁻¹ on the kept singular values,
    λ → ∞ the scaled gradient ``Jᵀ g / λ``. With ``relative`` (the default) the damping is
    measured in units of the largest squared singular value, ``λ = damping · σ_max²``, so
    one value means the same on problems whose physics differ by orders of magnitude in
    scale. ``damping`` may be a traced scalar (an adaptive rule's state).
    """

    damping: ArrayLike
    relative: bool = eqx.field(static=True, default=True)


def _kept_powers(s: Array, exponent: float | Damped, truncation: float, divided: bool = False) -> Array:
    """``f(s)`` (or ``f(s)/s`` with ``divided``) where ``s > truncation·max(s)``, else 0
    (dropped, not clamped); ``f(s) = s**exponent`` for a number, σ/(σ² + λ) for :class:`Damped`."""
    s_max = jnp.max(s)
    keep = s > truncation * s_max
    # Guard the power before the `where`: 0**negative would leak inf/NaN into gradients.
    safe = jnp.where(keep, s, jnp.ones_like(s))
    if isinstance(exponent, Damped):
        lam = exponent.damping * s_max**2 if exponent.relative else exponent.damping
        values = (1.0 if divided else safe) / (safe**2 + lam)
    else:
        values = safe ** (exponent - 1.0 if divided else exponent)
    return jnp.where(keep, values, jnp.zeros_like(s)).astype(s.dtype)


Spectrum = dict[str, Array]


def spectrum_stats(s: Array, truncation: float) -> Spectrum:
    """What the truncation kept of the singular values ``s`` (any order, ≥ 0):

    - ``rank``: the number kept, ``#{σ > τ σ_max}`` (int32);
    - ``sigma_max``: σ_max;
    - ``sigma_min_kept``: the smallest kept σ (``inf`` when none is kept, ``s`` all 0).

    With κ = −½ the kept range sets the spread of the step's scaling, σ_max^{−½} to
    σ_min_kept^{−½}."""
    s_max = jnp.max(s)
    keep = s > truncation * s_max
    return {"rank": jnp.sum(keep).astype(jnp.int32), "sigma_max": s_max,
            "sigma_min_kept": jnp.min(jnp.where(keep, s, jnp.inf))}  # fmt: skip


def cast_spectrum(spectrum: Spectrum, dtype) -> Spectrum:
    """The σ's of :func:`spectrum_stats` in ``dtype`` (a float64 scope's way out)."""
    return {k: v if k == "rank" else v.astype(dtype) for k, v in spectrum.items()}


def gram_power_and_spectrum(
    gram: Array, vector: Array, exponent: float | Damped, truncation: float
) -> tuple[Array, Spectrum]:
    """:func:`gram_power` and the :func:`spectrum_stats` of its singular values
    σ = √(eigenvalues of the Gram matrix)."""
    eigenvalues, vectors = jnp.linalg.eigh(gram)
    s = jnp.sqrt(jnp.clip(eigenvalues, 0.0, None))
    powers = _kept_powers(s, exponent, truncation, divided=True)
    return vectors @ (powers * (vectors.T @ vector)), spectrum_stats(s, truncation)


def gram_power(gram: Array, vector: Array, exponent: float | Damped, truncation: float) -> Array:
    """``U Σ^{κ−1} Uᵀ v`` for a Gram matrix ``U Σ² Uᵀ`` (``J Jᵀ`` or ``Jᵀ J``), singular
    values ``σ ≤ τ σ_max`` dropped. The one extra Σ⁻¹ turns the Gram eigenvectors into the
    missing SVD factor: ``J^κ g = Jᵀ·gram_power(J Jᵀ, g)`` = ``gram_power(Jᵀ J, Jᵀ g)``.
    With a :class:`Damped` filter: ``U (Σ² + λ)⁻¹ Uᵀ v``.

    Computes in the inputs' dtype; the Gram routes call it on float64 inside their scope."""
    return gram_power_and_spectrum(gram, vector, exponent, truncation)[0]


def _svd_route(jacobian, grad, exponent, truncation):
    u, s, vt = jnp.linalg.svd(jacobian, full_matrices=False)
    return vt.T @ (_kept_powers(s, exponent, truncation) * (u.T @ grad)), spectrum_stats(s, truncation)


def _gram_route(jacobian, grad, exponent, truncation):
    # Constants for differentiation: the float64 scope below cannot be transposed outside it.
    inputs = jax.lax.stop_gradient((jacobian, grad))
    with float64_scope():
        j, g = to_float64(inputs)
        m, p = j.shape
        if m <= p:  # wide: Jᵀ U Σ^{κ−1} Uᵀ g
            w, spectrum = gram_power_and_spectrum(j @ j.T, g, exponent, truncation)
            direction = j.T @ w
        else:  # tall: V Σ^{κ−1} Vᵀ Jᵀ g
            direction, spectrum = gram_power_and_spectrum(j.T @ j, j.T @ g, exponent, truncation)
        # Back to the Jacobian's dtype inside the scope: no float64 array leaves it.
        return direction.astype(jacobian.dtype), cast_spectrum(spectrum, jacobian.dtype)


def half_inverse(
    jacobian: Float[Array, "m p"],
    grad: Float[Array, " m"],
    *,
    exponent: float | Damped = -0.5,
    truncation: float = 1e-6,
    route: Route = "auto",
) -> Float[Array, " p"]:
    """Return ``V · diag(σ^exponent) · Uᵀ · grad`` over the retained singular values.

    Arguments:
        jacobian: ``J``, shape (m, P); for HIG the per-sample Jacobians of the simulator
            output stacked sample-major (m = batch × output size).
        grad: ``g``, shape (m,); the gradient of the batch-mean loss w.r.t. the outputs.
        exponent: κ; −0.5 half-inverse (HIG), −1 Gauss–Newton, +1 gives ``Jᵀ g``; or a
            :class:`Damped` filter (Levenberg–Marquardt).
        truncation: τ; singular values ``σ ≤ τ·σ_max`` are dropped.
        route: ``"svd"``, ``"gram"`` (float64 Gram + ``eigh``, scoped; not
            differentiable) or ``"auto"`` (by shape).

    Returns:
        The update direction, shape (P,), in the dtype of ``jacobian``. The caller takes
        the step ``θ ← θ − η · half_inverse(J, g)``.
    """
    return half_inverse_and_spectrum(jacobian, grad, exponent=exponent, truncation=truncation, route=route)[0]


def half_inverse_and_spectrum(
    jacobian: Float[Array, "m p"],
    grad: Float[Array, " m"],
    *,
    exponent: float | Damped = -0.5,
    truncation: float = 1e-6,
    route: Route = "auto",
) -> tuple[Float[Array, " p"], Spectrum]:
    """:func:`half_inverse` and what its truncation kept of J's singular values
    (:func:`spectrum_stats`: ``rank``, ``sigma_max``, ``sigma_min_kept``, the σ's in the
    Jacobian's dtype)."""
    if jacobian.ndim != 2 or grad.shape != jacobian.shape[:1]:
        raise ValueError(f"half_inverse needs jacobian (m, P) and grad (m,); got {jacobian.shape} and {grad.shape}")
    if route not in ROUTES:
        raise ValueError(f"unknown route {route!r}; valid choices: {', '.join(ROUTES)}")
    if route == "auto":
        rows, size = jacobian.shape
        route = choose_route((rows, size))
    solve = _svd_route if route == "svd" else _gram_route
    direction, spectrum = solve(jacobian, grad, exponent, truncation)
    return direction.astype(jacobian.dtype), cast_spectrum(spectrum, jacobian.dtype)


def sharded_gram_route(
    jacobian: Float[Array, "r p"],
    grad: Float[Array, " r"],
    axis: str,
    devices: int,
    *,
    exponent: float = -0.5,
    truncation: float = 1e-6,
) -> Float[Array, " p"]:
    """The Gram route with the Jacobian's rows spread over ``devices`` devices.

    Call inside ``jax.shard_map`` over mesh axis ``axis``: each device passes its own
    block ``J_i`` (r × P, the rows of the samples it owns, in sample order over the
    devices) and the matching entries ``g_i`` of the output gradient. ``J`` is never
    gathered; memory per device is the own block (in float64) and one visiting block.

    Wide ``J`` (m = devices·r ≤ P): the blocks travel once around a ring
    (``ppermute``, devices − 1 hops) so device i forms its strip ``G[i, :] = J_i Jᵀ``;
    the strips are all-gathered into ``G = J Jᵀ`` (m × m, float64), device 0 runs the
    one small ``eigh`` ``G = U Λ Uᵀ`` and ``w = U Λ^{(κ−1)/2} Uᵀ g`` (m,) is broadcast
    by a ``psum``; ``Jᵀ w = Σ_i J_iᵀ w_i`` is applied shard-wise with one ``psum`` of a
    P-vector.
    Tall ``J``: ``JᵀJ = Σ_i J_iᵀ J_i`` and ``Jᵀ g`` by ``psum``, then as the serial route
    (its eigendecomposition again on device 0 alone).

    Returns the direction ``J^κ g`` (P,), replicated, in the Jacobian's dtype. Equal to
    :func:`half_inverse` with ``route="gram"`` on the stacked rows up to the order of
    floating-point sums. Float64 is scoped as in :func:`half_inverse`, whose Gram route
    this is (inputs are constants for differentiation).
    """
    return sharded_gram_route_and_spectrum(jacobian, grad, axis, devices, exponent=exponent, truncation=truncation)[0]


def sharded_gram_route_and_spectrum(
    jacobian: Float[Array, "r p"],
    grad: Float[Array, " r"],
    axis: str,
    devices: int,
    *,
    exponent: float = -0.5,
    truncation: float = 1e-6,
) -> tuple[Float[Array, " p"], Spectrum]:
    """:func:`sharded_gram_route` and the :func:`spectrum_stats` of the whole J
    (replicated, the σ's in the Jacobian's dtype)."""
    inputs = jax.lax.stop_gradient((jacobian, grad))
    with float64_scope():
        direction, spectrum = _sharded_gram_route(*inputs, axis, devices, exponent, truncation)
        return direction, cast_spectrum(spectrum, jacobian.dtype)


def on_device_0(fn, *args, axis: str):
    """``fn(*args)`` computed on device 0 alone and given to every device by a ``psum``
    (the others add zeros). Replicating the small eigendecomposition would cost nothing on
    separate accelerators, but N times the work where devices share cores (forced host
    devices, several processes on one machine). Call in a float64 scope."""
    me = jax.lax.axis_index(axis)
    # Both branches must be typed as varying over the devices: adding a device-varying
    # zero makes them so whether fn's result already is or not. fn may return a pytree.
    vary = jax.lax.pcast(jnp.zeros((), jnp.float64), axis, to="varying")

    def varying(x):
        return x + vary.astype(x.dtype)

    def zeros(*a):
        return jax.tree.map(lambda s: varying(jnp.zeros(s.shape, s.dtype)), jax.eval_shape(fn, *a))

    return jax.lax.psum(jax.lax.cond(me == 0, lambda *a: jax.tree.map(varying, fn(*a)), zeros, *args), axis)


def ring_gram(block, cross, rows: int, axis: str, devices: int) -> Array:
    """The whole Gram matrix ``G`` (m × m, m = devices · rows) from row blocks spread over
    the devices, never gathering the blocks: each device's ``block`` (any pytree: Jacobian
    rows, or their factors) travels once around a ring (``ppermute``, devices − 1 hops),
    device i forms its strip ``G[i, :]`` as ``cross(own, visiting)`` (rows × rows, float64)
    and the strips are all-gathered. Call inside ``shard_map`` and a float64 scope."""
    me = jax.lax.axis_index(axis)
    ring = [(k, (k + 1) % devices) for k in range(devices)]
    strip = jnp.zeros((rows, rows * devices), jnp.float64)
    visiting = block
    for hop in range(devices):  # after `hop` hops this device holds the block of device me − hop
        owner = (me - hop) % devices
        strip = jax.lax.dynamic_update_slice_in_dim(strip, cross(block, visiting), owner * rows, axis=1)
        if hop < devices - 1:
            visiting = jax.lax.ppermute(visiting, axis, ring)
    return jax.lax.all_gather(strip, axis, tiled=True)


def _sharded_gram_route(jacobian, grad, axis, devices, exponent, truncation):
    """:func:`sharded_gram_route`'s body, run inside its float64 scope."""
    j, g = to_float64((jacobian, grad))
    r, p = j.shape
    me = jax.lax.axis_index(axis)

    def direction(gram, vector):  # U Σ^{κ−1} Uᵀ v and the spectrum
        return gram_power_and_spectrum(gram, vector, exponent, truncation)

    if r * devices > p:  # tall: the P × P Gram matrix is a sum over devices; V Σ^{κ−1} Vᵀ Jᵀ g
        gram, jtg = jax.lax.psum(j.T @ j, axis), jax.lax.psum(j.T @ g, axis)
        d, spectrum = on_device_0(direction, gram, jtg, axis=axis)
        return d.astype(jacobian.dtype), spectrum
    # The visiting blocks travel in their own dtype (half the bytes of float64 for float32 nets).
    gram = ring_gram(jacobian, lambda _, visiting: j @ visiting.astype(jnp.float64).T, r, axis, devices)
    g_all = jax.lax.all_gather(g, axis, tiled=True)
    w, spectrum = on_device_0(direction, gram, g_all, axis=axis)  # w = U Λ^{(κ−1)/2} Uᵀ g
    own = jax.lax.dynamic_slice_in_dim(w, me * r, r)
    return jax.lax.psum(j.T @ own, axis).astype(jacobian.dtype), spectrum

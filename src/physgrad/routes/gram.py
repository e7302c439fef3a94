"""The Gram route: eigendecomposition of the smaller Gram matrix in float64, on one device
or with J's rows spread over a device mesh (a ring of row blocks).

For a wide ``J`` (m ≤ P), ``J Jᵀ = U Σ² Uᵀ`` and ``J^κ g = Jᵀ U Σ^{κ−1} Uᵀ g``; for a
tall ``J``, ``Jᵀ J = V Σ² Vᵀ`` and ``J^κ g = V Σ^{κ−1} Vᵀ Jᵀ g`` (:func:`.spectrum.gram_power`).
The Gram matrix squares the condition number, which is why it is formed and decomposed
in float64. This never forms the large factor (``V`` for wide, ``U`` for tall) and costs
one matrix product of O(min(m,P)² · max(m,P)) plus an O(min(m,P)³) ``eigh``.

The float64 is scoped (:func:`physgrad.precision.float64_scope`): it works whether or not
the user enabled ``jax_enable_x64`` and leaves that setting alone. A scoped region cannot
be differentiated (its transpose would run outside the scope), so the route treats its
inputs as constants (``stop_gradient``): the direction is an update, never differentiated
by an update rule.

Sharded (:func:`sharded_gram_route`, inside ``jax.shard_map`` over the data axis): each
device holds the rows ``J_i`` (r × P) of its own samples. Wide J (m = devices·r ≤ P): the
blocks travel once around a ring (``ppermute``, devices − 1 hops) so device i forms its
strip ``G[i, :] = J_i Jᵀ`` (:func:`ring_gram`); the strips are all-gathered into
``G = J Jᵀ`` (m × m, float64), device 0 runs the one small ``eigh`` (:func:`on_device_0`)
and ``w = U Λ^{(κ−1)/2} Uᵀ g`` (m,) is broadcast by a ``psum``; ``Jᵀ w = Σ_i J_iᵀ w_i`` is
applied shard-wise with one ``psum`` of a P-vector. Tall J: ``JᵀJ = Σ_i J_iᵀ J_i`` and
``Jᵀ g`` by ``psum``, then as one device. J is never gathered; memory per device is the own
block (in float64) and one visiting block.

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..distributed import AXIS, data_axis_size
from ..precision import float64_scope, to_float64
from .base import F64, AbstractRoute, JointJacobian, over_devices
from .spectrum import Damped, Spectrum, cast_spectrum, gram_power


class Gram(AbstractRoute):
    """Float64 Gram matrix + ``eigh`` (exact); sharded over the rows under a device mesh."""

    code = 1

    def power(
        self, jacobian: Float[Array, "m p"], grad: Float[Array, " m"], exponent: float | Damped, truncation: float
    ) -> tuple[Float[Array, " p"], Spectrum]:
        """``J^κ g`` of an explicit J and its :func:`~.spectrum.spectrum_stats` (in J's dtype)."""
        # Constants for differentiation: the float64 scope below cannot be transposed outside it.
        inputs = jax.lax.stop_gradient((jacobian, grad))
        with float64_scope():
            j, g = to_float64(inputs)
            m, p = j.shape
            if m <= p:  # wide: Jᵀ U Σ^{κ−1} Uᵀ g
                w, spectrum = gram_power(j @ j.T, g, exponent, truncation)
                direction = j.T @ w
            else:  # tall: V Σ^{κ−1} Vᵀ Jᵀ g
                direction, spectrum = gram_power(j.T @ j, j.T @ g, exponent, truncation)
            # Back to the Jacobian's dtype inside the scope: no float64 array leaves it.
            return direction.astype(jacobian.dtype), cast_spectrum(spectrum, jacobian.dtype)

    def compute(self, jacobian: JointJacobian, exponent, truncation):
        devices = data_axis_size()
        if devices == 1:
            jac, g, loss = jacobian.jacobian_and_gradient()
            direction, spectrum = self.power(jac, g, exponent, truncation)
            return direction, loss, self.stats(spectrum)
        # Data parallel: each device forms the Jacobian rows of its own samples and the
        # Gram matrix is assembled by collectives (sharded_gram_route).
        direction, loss, spectrum = over_devices(_sharded_direction, jacobian, devices, exponent, truncation)
        return direction, loss, self.stats(spectrum)

    def footprint_of(self, jacobian, devices=1):
        rows, size = jacobian.shape
        # the device's rows of J in its dtype and in float64, plus the Gram-side matrices
        return -(-rows // devices) * size * (jacobian.itemsize + F64) + gram_bytes(jacobian.shape)


def gram_bytes(shape: tuple[int, int]) -> int:
    """The float64 Gram matrix (m × m, m = the smaller side), its eigenvectors and
    ``eigh``'s workspace on every device (the ring all-gathers the whole matrix)."""
    m = min(shape)
    return 3 * m * m * F64


def sharded_gram_route(
    jacobian: Float[Array, "r p"],
    grad: Float[Array, " r"],
    axis: str,
    devices: int,
    *,
    exponent: float | Damped = -0.5,
    truncation: float = 1e-6,
) -> tuple[Float[Array, " p"], Spectrum]:
    """The Gram route with the Jacobian's rows spread over ``devices`` devices (module
    docstring): call inside ``jax.shard_map`` over mesh axis ``axis``, each device passing
    its own block ``J_i`` (r × P, its samples' rows, in sample order over the devices) and
    the matching entries ``g_i``.

    Returns the direction ``J^κ g`` (P,) and the :func:`~.spectrum.spectrum_stats` of the
    whole J, replicated, in the Jacobian's dtype; equal to :meth:`Gram.power` on the
    stacked rows up to the order of floating-point sums."""
    j, g = jax.lax.stop_gradient((jacobian, grad))
    with float64_scope():
        j64, g64 = to_float64((j, g))
        r, p = j.shape
        me = jax.lax.axis_index(axis)

        def direction(gram, vector):  # U Σ^{κ−1} Uᵀ v and the spectrum
            return gram_power(gram, vector, exponent, truncation)

        if r * devices > p:  # tall: the P × P Gram matrix is a sum over devices; V Σ^{κ−1} Vᵀ Jᵀ g
            gram, jtg = jax.lax.psum(j64.T @ j64, axis), jax.lax.psum(j64.T @ g64, axis)
            d, spectrum = on_device_0(direction, gram, jtg, axis=axis)
        else:
            # The visiting blocks travel in their own dtype (half the bytes of float64 for float32 nets).
            gram = ring_gram(j, lambda _, visiting: j64 @ visiting.astype(jnp.float64).T, r, axis, devices)
            g_all = jax.lax.all_gather(g64, axis, tiled=True)
            w, spectrum = on_device_0(direction, gram, g_all, axis=axis)  # w = U Λ^{(κ−1)/2} Uᵀ g
            own = jax.lax.dynamic_slice_in_dim(w, me * r, r)
            d = jax.lax.psum(j64.T @ own, axis)
        return d.astype(jacobian.dtype), cast_spectrum(spectrum, jacobian.dtype)


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


def _sharded_direction(objective, params, batch, *, devices, exponent, truncation):
    # Mark the replicated parameters as varying over the devices: differentiating
    # w.r.t. an invariant input would psum the per-device Jacobians (shard_map's
    # transpose of the implicit broadcast), and each device must keep its own rows.
    params = jax.lax.pcast(params, AXIS, to="varying")
    jac, g, loss = JointJacobian.of(objective, params, batch).jacobian_and_gradient(devices)
    direction, spectrum = sharded_gram_route(jac, g, AXIS, devices, exponent=exponent, truncation=truncation)
    return direction, jax.lax.psum(loss, AXIS), spectrum

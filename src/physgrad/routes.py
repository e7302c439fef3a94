"""How the κ-power of the joint Jacobian is computed: interchangeable route objects.

Gauss–Newton and half-inverse gradients need ``J^κ g = V Σ^κ Uᵀ g`` for the joint
per-sample Jacobian ``J = ∂y/∂θ`` (rows = batch × output size, columns = parameters) and
the output gradient ``g = ∂L/∂y`` (:mod:`physgrad.half_inverse`). A route decides how,
like lineax's solvers decide how a linear system is solved:

- :class:`SVD`: thin SVD of J in its own dtype (the paper's way);
- :class:`Gram`: eigendecomposition of the smaller Gram matrix in float64 (exact, far
  cheaper whenever J is clearly wide or tall); under a device mesh each device forms the
  Jacobian rows of its own samples and the Gram matrix is assembled by collectives;
- :class:`BlockGram`: the exact Gram matrix from sample groups' Jacobians, recomputed pair
  by pair, so only two groups' rows are ever held (J too large for memory);
- :class:`Lanczos`: a Krylov approximation from Jacobian–vector products (never forms J;
  accurate only for well-conditioned spectra);
- :class:`Structured`: the exact Gram matrix from each dense layer's back-propagated
  signals and inputs (:mod:`physgrad.structured`), explicit rows only for the other
  parameters: never holds J, and costs ``rows² · (Σ d_out + P_other)`` instead of
  ``rows² · P``;
- :class:`Auto`: :class:`Structured` when the network has dense layers and J is wide,
  else :class:`Gram` or :class:`SVD` by the shape of J (the default).

Every route also estimates the memory of its own large arrays (``footprint``), which the
training engine checks against the device before the first step.

Every route returns ``(direction, loss, stats)``: the flat direction (P,), the batch-mean
loss and statistics of the step, numbers the training engine averages into
``metrics.csv`` (``step_<name>``):

- ``route``: the route that ran, as its index in :data:`ROUTE_NAMES` (``Auto()`` decides
  at trace time from shapes; :meth:`Auto.choose` names it without computing anything);
- ``rank``: the number of singular values kept, ``#{σ > τ σ_max}``;
- ``sigma_max`` and ``sigma_min_kept``: the largest and the smallest kept singular value of
  J (Lanczos: of its Ritz approximation, which resolves the top of the spectrum first);
- Lanczos also logs ``lanczos_change``.
"""

from __future__ import annotations

import abc
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec
from jaxtyping import Array

from . import structured
from .distributed import AXIS, data_axis_size
from .half_inverse import (
    cast_spectrum,
    choose_route,
    gram_power_and_spectrum,
    half_inverse_and_spectrum,
    on_device_0,
    ring_gram,
    sharded_gram_route_and_spectrum,
)
from .half_inverse_large import (
    batch_output_map,
    blockgram_half_inverse_and_spectrum,
    lanczos_half_inverse_and_spectrum,
)
from .jacobian import flat_output, stacked_jacobian
from .precision import float64_scope, to_float64

_F64 = 8  # bytes of a float64

ROUTE_NAMES = ("svd", "gram", "structured", "blockgram", "lanczos")
"""The routes by the code a step's ``stats["route"]`` holds: ``ROUTE_NAMES[code]``."""


def _with_route(name: str, stats: dict) -> dict:
    return {"route": jnp.asarray(ROUTE_NAMES.index(name), jnp.int32), **stats}


class AbstractRoute(eqx.Module):
    """``route(objective, params, batch, exponent, truncation) -> (direction, loss, stats)``."""

    @abc.abstractmethod
    def __call__(
        self, objective, params, batch, exponent: float, truncation: float
    ) -> tuple[Array, Array, dict[str, Array]]: ...

    def check_batch_size(self, batch_size: int) -> None:
        """Raise ``ValueError`` if the route cannot take batches of this size."""

    def footprint(self, objective, params, batch, devices: int = 1) -> int:
        """Bytes per device of the route's own large arrays for this (global) batch spread
        over ``devices`` devices, from shapes alone (nothing is computed); 0 when the
        route cannot tell."""
        return 0

    def name(self) -> str:
        return type(self).__name__.lower()


class SVD(AbstractRoute):
    """Thin SVD of the whole J (float32 for float32 networks). Under a mesh XLA gathers J."""

    def footprint(self, objective, params, batch, devices=1):
        (rows, size), itemsize = jacobian_shape(objective, params, batch), _itemsize(params)
        # J, its copy in the factorisation and the thin factors U (rows × k), V (P × k).
        return (2 * rows * size + min(rows, size) * (rows + size)) * itemsize

    def __call__(self, objective, params, batch, exponent, truncation):
        jac, g, loss = jacobian_and_gradient(objective, params, batch)
        direction, spectrum = half_inverse_and_spectrum(jac, g, exponent=exponent, truncation=truncation, route="svd")
        return direction, loss, _with_route("svd", spectrum)


class Gram(AbstractRoute):
    """Float64 Gram matrix + ``eigh`` (exact); sharded over the rows under a device mesh."""

    def __call__(self, objective, params, batch, exponent, truncation):
        devices = data_axis_size()
        if devices == 1:
            jac, g, loss = jacobian_and_gradient(objective, params, batch)
            direction, spectrum = half_inverse_and_spectrum(
                jac, g, exponent=exponent, truncation=truncation, route="gram"
            )
            return direction, loss, _with_route("gram", spectrum)
        # Data parallel: each device forms the Jacobian rows of its own samples and the
        # Gram matrix is assembled by collectives (half_inverse.sharded_gram_route).
        direction, loss, spectrum = _over_devices(
            _sharded_direction, objective, params, batch, devices, exponent, truncation
        )
        return direction, loss, _with_route("gram", spectrum)

    def footprint(self, objective, params, batch, devices=1):
        rows, size = jacobian_shape(objective, params, batch)
        # the device's rows of J in its dtype and in float64, plus the Gram-side matrices
        j = -(-rows // devices) * size * (_itemsize(params) + _F64)
        return j + _gram_bytes((rows, size))


class Structured(AbstractRoute):
    """The exact Gram matrix ``J Jᵀ`` from layer structure (:mod:`physgrad.structured`).

    Each dense layer contributes ``(D Dᵀ) ⊙ (A Aᵀ)⇑`` from its back-propagated signals D
    (rows × d_out) and inputs A (samples × d_in); the other parameters contribute their
    explicit Jacobian rows, ``chunk_elements`` numbers at a time. Products accumulate in
    float64, the kept eigenpairs are as :class:`Gram`'s and ``Jᵀ w`` comes from the same
    factors, so the update equals :class:`Gram`'s without ever holding J. A tall J
    (rows > P) goes to :class:`Gram`. Under a device mesh each device keeps its rows'
    factors and the ring passes D, A and the explicit rows instead of rows of J."""

    chunk_elements: int = eqx.field(static=True, default=structured.CHUNK_ELEMENTS)

    def __call__(self, objective, params, batch, exponent, truncation):
        rows, size = jacobian_shape(objective, params, batch)
        if rows > size:
            return Gram()(objective, params, batch, exponent, truncation)
        devices = data_axis_size()
        if devices == 1:
            out = _structured_direction(objective, params, batch, self.chunk_elements, exponent, truncation)
        else:
            out = _over_devices(_sharded_structured, objective, params, batch, devices, exponent, truncation)
        direction, loss, spectrum = out
        return direction, loss, _with_route("structured", spectrum)

    def footprint(self, objective, params, batch, devices=1):
        rows, size = jacobian_shape(objective, params, batch)
        if rows > size:
            return Gram().footprint(objective, params, batch, devices)
        plan = _structure(objective, params, batch, self.chunk_elements)
        b = jax.tree.leaves(batch)[0].shape[0]
        local_rows, local_b = -(-rows // devices), -(-b // devices)
        per_byte = _itemsize(params) + _F64
        d_out, d_in = sum(u.d_out for u in plan.dense), sum(u.d_in for u in plan.dense)
        group = max((sum(plan.leaf_sizes[k] for k in g) for g in plan.groups), default=0)
        explicit = plan.explicit_parameters if devices > 1 else group
        return (local_rows * (d_out + explicit) + local_b * d_in) * per_byte + _gram_bytes((rows, size))


class Auto(AbstractRoute):
    """:class:`Structured` when J is wide (rows ≤ P/2) and the network has dense layers;
    otherwise :class:`Gram` when one side of J is at least twice the other, else
    :class:`SVD`; decided on the shape of the whole J (as on one device)."""

    def choose(self, objective, params, batch) -> AbstractRoute:
        rows, size = jacobian_shape(objective, params, batch)
        if choose_route((rows, size)) == "svd":
            return SVD()
        if rows <= size and _structure(objective, params, batch).dense:
            return Structured()
        return Gram()

    def __call__(self, objective, params, batch, exponent, truncation):
        return self.choose(objective, params, batch)(objective, params, batch, exponent, truncation)

    def footprint(self, objective, params, batch, devices=1):
        return self.choose(objective, params, batch).footprint(objective, params, batch, devices)


class BlockGram(AbstractRoute):
    """Exact Gram matrix from ``blocks`` sample groups, two groups' Jacobians at a time.

    Never forms J: memory two groups' rows × P plus m². Under a mesh XLA partitions what
    it can; the groups are indexed dynamically, so it may repeat work on every device."""

    blocks: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        if self.blocks < 1:
            raise ValueError(f"blocks must be >= 1, got {self.blocks}")

    def check_batch_size(self, batch_size):
        if batch_size % self.blocks:
            raise ValueError(f"route blockgram needs blocks ({self.blocks}) to divide the batch size {batch_size}")

    def __call__(self, objective, params, batch, exponent, truncation):
        self.check_batch_size(jax.tree.leaves(batch)[0].shape[0])
        g, loss = output_gradient(objective, params, batch)
        direction, spectrum = blockgram_half_inverse_and_spectrum(
            objective.predict, params, batch, g, blocks=self.blocks, exponent=exponent, truncation=truncation
        )
        return direction, loss, _with_route("blockgram", spectrum)

    def footprint(self, objective, params, batch, devices=1):
        rows, size = jacobian_shape(objective, params, batch)
        two_groups = 2 * -(-rows // self.blocks) * size * (_itemsize(params) + _F64)
        return two_groups + _gram_bytes((rows, size))


class Lanczos(AbstractRoute):
    """``steps`` Lanczos steps on J Jᵀ through JVP/VJP products (approximate; exact at
    steps = rows). Logs ``lanczos_change``, the relative change of the last step."""

    steps: int = eqx.field(static=True, default=64)

    def __check_init__(self):
        if self.steps < 1:
            raise ValueError(f"lanczos steps must be >= 1, got {self.steps}")

    def __call__(self, objective, params, batch, exponent, truncation):
        g, loss = output_gradient(objective, params, batch)
        direction, change, spectrum = lanczos_half_inverse_and_spectrum(
            objective.predict, params, batch, g, steps=self.steps, exponent=exponent, truncation=truncation
        )
        return direction, loss, _with_route("lanczos", {**spectrum, "lanczos_change": change})

    def footprint(self, objective, params, batch, devices=1):
        rows, size = jacobian_shape(objective, params, batch)
        return 2 * self.steps * (rows + size) * _F64


def _over_devices(local, objective, params, batch, devices, exponent, truncation):
    """``local(objective, params, batch, devices=, exponent=, truncation=)`` run by every
    device on its share of the batch (``shard_map``), parameters replicated; returns the
    replicated ``(direction, loss, spectrum)``."""
    spec = PartitionSpec(AXIS)
    body = functools.partial(local, objective, devices=devices, exponent=exponent, truncation=truncation)
    return jax.shard_map(body, in_specs=(PartitionSpec(), spec), out_specs=PartitionSpec())(params, batch)


def _itemsize(params) -> int:
    leaves = jax.tree.leaves(params)
    return max((jnp.dtype(x.dtype).itemsize for x in leaves), default=4)


def jacobian_shape(objective, params, batch) -> tuple[int, int]:
    """(rows, P) of the whole stacked Jacobian, from shapes alone."""
    sample = jax.tree.map(lambda a: a[0], batch)
    out = jax.eval_shape(lambda p, s: flat_output(objective.predict(p, s)), params, sample)
    b = jax.tree.leaves(batch)[0].shape[0]
    return b * out.size, sum(x.size for x in jax.tree.leaves(params))


def _gram_bytes(shape: tuple[int, int]) -> int:
    """The float64 Gram matrix (m × m, m = the smaller side), its eigenvectors and
    ``eigh``'s workspace on every device (the ring all-gathers the whole matrix)."""
    m = min(shape)
    return 3 * m * m * _F64


def _structure(objective, params, batch, chunk_elements: int = structured.CHUNK_ELEMENTS):
    sample = jax.tree.map(lambda a: a[0], batch)
    rows, _ = jacobian_shape(objective, params, batch)
    return structured.find_structure(objective.predict, params, sample, rows, chunk_elements)


def _assemble(params, pieces: dict, cast: bool = True) -> jax.Array:
    """The flat direction (P,) in ``ravel_pytree`` order from per-leaf pieces (cast to
    each leaf's dtype, or kept as they are)."""
    leaves = jax.tree.leaves(params)
    return jnp.concatenate(
        [pieces[k].reshape(-1).astype(x.dtype if cast else pieces[k].dtype) for k, x in enumerate(leaves)]
    )


def _structured_direction(objective, params, batch, chunk_elements, exponent, truncation):
    """One device: the Gram matrix group by group, ``w = U Σ^{κ−1} Uᵀ g``, then ``Jᵀ w``."""
    plan = _structure(objective, params, batch, chunk_elements)
    block, y = structured.factors(plan, params, batch, groups=(0,))
    loss, g = loss_and_output_gradient(objective, params, batch, y)
    whole = len(plan.groups) <= 1  # the first pass holds every explicit row
    # Constants for differentiation: the float64 scopes below cannot be transposed.
    block, g = jax.lax.stop_gradient((block, g))
    with float64_scope():
        gram = structured.cross_gram(plan, block, block)
    for group in range(1, len(plan.groups)):
        rows = jax.lax.stop_gradient(structured.explicit_rows(objective.predict, plan, params, batch, group))
        with float64_scope():
            rows = to_float64(rows)
            gram = gram + rows @ rows.T
    with float64_scope():
        w, spectrum = gram_power_and_spectrum(gram, to_float64(g), exponent, truncation)
        pieces = structured.transpose_product(plan, block, w, plan.groups[0] if whole and plan.groups else ())
        leaves = jax.tree.leaves(params)
        pieces = {k: v.astype(leaves[k].dtype) for k, v in pieces.items()}
        w = w.astype(y.dtype)
        spectrum = cast_spectrum(spectrum, y.dtype)
    if not whole:
        rest = tuple(k for group in plan.groups for k in group)
        pieces.update(structured.vjp_leaves(objective.predict, plan, jax.lax.stop_gradient(params), batch, w, rest))
    return _assemble(params, pieces), loss, spectrum


def _sharded_structured(objective, params, batch, *, devices, exponent, truncation):
    """Data parallel: each device keeps its rows' factors (all explicit rows in one block)
    and the ring passes them (rows/N × (Σ d_out + P_explicit) + samples/N × Σ d_in numbers
    per hop instead of rows/N × P)."""
    params = jax.lax.pcast(params, AXIS, to="varying")  # each device keeps its own rows (see _sharded_direction)
    plan = _structure(objective, params, batch, chunk_elements=2**62)
    block, y = structured.factors(plan, params, batch, groups=tuple(range(len(plan.groups))), axis=AXIS)
    loss, g = loss_and_output_gradient(objective, params, batch, y, devices)
    block, g = jax.lax.stop_gradient((block, g))
    r = g.shape[0]
    explicit = tuple(k for group in plan.groups for k in group)
    me = jax.lax.axis_index(AXIS)
    with float64_scope():
        gram = ring_gram(block, functools.partial(structured.cross_gram, plan), r, AXIS, devices)
        g_all = jax.lax.all_gather(to_float64(g), AXIS, tiled=True)
        w, spectrum = on_device_0(
            lambda G, v: gram_power_and_spectrum(G, v, exponent, truncation), gram, g_all, axis=AXIS
        )
        own = jax.lax.dynamic_slice_in_dim(w, me * r, r)
        pieces = structured.transpose_product(plan, block, own, explicit)
        direction = jax.lax.psum(_assemble(params, pieces, cast=False), AXIS)
        direction = direction.astype(jax.tree.leaves(params)[0].dtype)
        spectrum = cast_spectrum(spectrum, direction.dtype)
    return direction, jax.lax.psum(loss, AXIS), spectrum


def output_gradient(objective, params, batch):
    """``g = ∂L/∂y`` (rows,) and the batch-mean loss, without J."""
    outputs, flat = batch_output_map(objective.predict, params, batch)
    b = jax.tree.leaves(batch)[0].shape[0]
    return loss_and_output_gradient(objective, params, batch, outputs(flat).reshape(b, -1))[::-1]


def jacobian_and_gradient(objective, params, batch, devices: int = 1):
    """``J`` (rows, P), ``g = ∂L/∂y`` (rows,) and this batch's share of the loss
    ``L = mean over the global batch`` (the batch is 1/devices of it)."""
    jac, y = stacked_jacobian(objective.predict, params, batch)
    loss, g = loss_and_output_gradient(objective, params, batch, y, devices)
    return jac, g, loss


def _sharded_direction(objective, params, batch, *, devices, exponent, truncation):
    # Mark the replicated parameters as varying over the devices: differentiating
    # w.r.t. an invariant input would psum the per-device Jacobians (shard_map's
    # transpose of the implicit broadcast), and each device must keep its own rows.
    params = jax.lax.pcast(params, AXIS, to="varying")
    jac, g, loss = jacobian_and_gradient(objective, params, batch, devices)
    direction, spectrum = sharded_gram_route_and_spectrum(
        jac, g, AXIS, devices, exponent=exponent, truncation=truncation
    )
    return direction, jax.lax.psum(loss, AXIS), spectrum


def loss_and_output_gradient(objective, params, batch, y, devices: int = 1):
    """The batch-mean loss (divided by ``devices``: a device's share of the global mean)
    and its gradient w.r.t. the flat outputs ``y`` (b, d), raveled sample-major."""
    unflatten_y = _output_unflattener(objective, params, batch)

    def mean_loss(y_flat):
        # y_flat holds the flattened outputs; losses see them in the predict shape.
        return jnp.mean(jax.vmap(objective.loss)(unflatten_y(y_flat), batch)) / devices

    loss, g = jax.value_and_grad(mean_loss)(y)
    return loss, g.ravel()


def _output_unflattener(objective, params, batch):
    """Map the flat (b, d) outputs of ``stacked_jacobian`` back to the predict shape."""
    sample = jax.tree.map(lambda a: a[0], batch)
    shape = jax.eval_shape(objective.predict, params, sample)

    def unflatten(y_flat):
        if jnp.issubdtype(shape.dtype, jnp.complexfloating):
            pairs = y_flat.reshape(y_flat.shape[0], *shape.shape, 2)
            return (pairs[..., 0] + 1j * pairs[..., 1]).astype(shape.dtype)
        return y_flat.reshape(y_flat.shape[0], *shape.shape)

    return unflatten

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
- :class:`Auto`: :class:`Gram` or :class:`SVD` by the shape of J (the default).

Every route returns ``(direction, loss, stats)``: the flat direction (P,), the batch-mean
loss and extra statistics (Lanczos logs ``lanczos_change``).
"""

from __future__ import annotations

import abc
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec

from .distributed import AXIS, data_axis_size
from .half_inverse import choose_route, half_inverse, sharded_gram_route
from .half_inverse_large import batch_output_map, blockgram_half_inverse, lanczos_half_inverse
from .jacobian import stacked_jacobian


class AbstractRoute(eqx.Module):
    """``route(objective, params, batch, exponent, truncation) -> (direction, loss, stats)``."""

    @abc.abstractmethod
    def __call__(self, objective, params, batch, exponent: float, truncation: float): ...

    def check_batch_size(self, batch_size: int) -> None:
        """Raise ``ValueError`` if the route cannot take batches of this size."""


class SVD(AbstractRoute):
    """Thin SVD of the whole J (float32 for float32 networks). Under a mesh XLA gathers J."""

    def __call__(self, objective, params, batch, exponent, truncation):
        jac, g, loss = jacobian_and_gradient(objective, params, batch)
        return half_inverse(jac, g, exponent=exponent, truncation=truncation, route="svd"), loss, {}


class Gram(AbstractRoute):
    """Float64 Gram matrix + ``eigh`` (exact); sharded over the rows under a device mesh."""

    def __call__(self, objective, params, batch, exponent, truncation):
        devices = data_axis_size()
        if devices == 1:
            jac, g, loss = jacobian_and_gradient(objective, params, batch)
            return half_inverse(jac, g, exponent=exponent, truncation=truncation, route="gram"), loss, {}
        # Data parallel: each device forms the Jacobian rows of its own samples and the
        # Gram matrix is assembled by collectives (half_inverse.sharded_gram_route).
        spec = PartitionSpec(AXIS)
        local = functools.partial(_sharded_direction, objective, devices=devices, exponent=exponent, truncation=truncation)
        direction, loss = jax.shard_map(local, in_specs=(PartitionSpec(), spec), out_specs=PartitionSpec())(params, batch)
        return direction, loss, {}


class Auto(AbstractRoute):
    """:class:`Gram` when one side of J is at least twice the other, else :class:`SVD`,
    decided on the shape of the whole J (as on one device)."""

    def __call__(self, objective, params, batch, exponent, truncation):
        shape = jax.eval_shape(lambda p, b: stacked_jacobian(objective.predict, p, b)[0], params, batch).shape
        route = Gram() if choose_route(shape) == "gram" else SVD()
        return route(objective, params, batch, exponent, truncation)


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
        direction = blockgram_half_inverse(
            objective.predict, params, batch, g, blocks=self.blocks, exponent=exponent, truncation=truncation
        )
        return direction, loss, {}


class Lanczos(AbstractRoute):
    """``steps`` Lanczos steps on J Jᵀ through JVP/VJP products (approximate; exact at
    steps = rows). Logs ``lanczos_change``, the relative change of the last step."""

    steps: int = eqx.field(static=True, default=64)

    def __check_init__(self):
        if self.steps < 1:
            raise ValueError(f"lanczos steps must be >= 1, got {self.steps}")

    def __call__(self, objective, params, batch, exponent, truncation):
        g, loss = output_gradient(objective, params, batch)
        direction, change = lanczos_half_inverse(
            objective.predict, params, batch, g, steps=self.steps, exponent=exponent, truncation=truncation
        )
        return direction, loss, {"lanczos_change": change}


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
    direction = sharded_gram_route(jac, g, AXIS, devices, exponent=exponent, truncation=truncation)
    return direction, jax.lax.psum(loss, AXIS)


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

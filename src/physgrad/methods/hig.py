"""Half-inverse gradients (HIG) and Gauss–Newton: κ-powers of the joint Jacobian.

Source: Schnell, Holl, Thuerey, *Half-Inverse Gradients for Physical Deep Learning*,
ICLR 2022; hig.md §1.

With ``J = ∂y/∂θ`` the per-sample Jacobians of the *simulator output* stacked
sample-major (rows = b · dim y, columns = all network parameters) and
``g = ∂L/∂y`` the gradient of the batch-mean loss w.r.t. the outputs,

    Δθ = −η · V Σ^κ Uᵀ g,      J = U Σ Vᵀ (thin SVD, σ ≤ τ σ_max dropped),

with κ = −½ (HIG) or κ = −1 (Gauss–Newton), applied by plain SGD (the paper's Keras SGD,
no momentum). The step is an optax transformation, so clipping or schedules compose.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree
from jax.sharding import PartitionSpec

from ..distributed import AXIS, data_axis_size
from ..half_inverse import ROUTES, choose_route, half_inverse, sharded_gram_route
from ..half_inverse_large import batch_output_map, blockgram_half_inverse, lanczos_half_inverse
from ..jacobian import stacked_jacobian
from .base import AbstractMethod


MATRIX_FREE = ("blockgram", "lanczos")
METHOD_ROUTES = ROUTES + MATRIX_FREE


class JacobianPower(AbstractMethod):
    """``θ ← θ + optimizer(J^κ g)`` with the joint stacked Jacobian (HIG for κ = −½)."""

    exponent: float = eqx.field(static=True)
    truncation: float = eqx.field(static=True)
    route: str = eqx.field(static=True)
    optimizer: optax.GradientTransformation = eqx.field(static=True)
    blocks: int = eqx.field(static=True, default=8)
    lanczos_steps: int = eqx.field(static=True, default=64)

    def __check_init__(self):
        if self.route not in METHOD_ROUTES:
            raise ValueError(f"unknown route {self.route!r}; valid choices: {', '.join(METHOD_ROUTES)}")
        if not self.truncation >= 0:
            raise ValueError(f"truncation must be >= 0, got {self.truncation}")
        if self.blocks < 1 or self.lanczos_steps < 1:
            raise ValueError(f"blocks and lanczos_steps must be >= 1, got {self.blocks} and {self.lanczos_steps}")

    def init(self, params):
        return self.optimizer.init(params)

    def check_batch_size(self, batch_size):
        if self.route == "blockgram" and batch_size % self.blocks:
            raise ValueError(f"route blockgram needs blocks ({self.blocks}) to divide the batch size {batch_size}")

    def step(self, objective, params, state, batch):
        devices = data_axis_size()
        stats = {}
        route = self.route
        if route == "auto":  # by the shape of the whole J, as on one device
            jac_shape = jax.eval_shape(lambda p, b: stacked_jacobian(objective.predict, p, b)[0], params, batch)
            route = choose_route(jac_shape.shape)
        if route in MATRIX_FREE:
            # Never forms J. Under a mesh XLA partitions what it can; the sample groups are
            # indexed dynamically, so it may repeat work on every device.
            self.check_batch_size(jax.tree.leaves(batch)[0].shape[0])
            g, loss = self._output_gradient(objective, params, batch)
            settings = dict(exponent=self.exponent, truncation=self.truncation)
            if route == "blockgram":
                direction = blockgram_half_inverse(objective.predict, params, batch, g, blocks=self.blocks, **settings)
            else:
                direction, stats["lanczos_change"] = lanczos_half_inverse(
                    objective.predict, params, batch, g, steps=self.lanczos_steps, **settings
                )
        elif devices > 1 and route == "gram":
            # Data parallel: each device forms the Jacobian rows of its own samples and
            # the Gram matrix is assembled by collectives (half_inverse.sharded_gram_route).
            spec = PartitionSpec(AXIS)
            local = functools.partial(self._sharded_direction, objective, devices=devices)
            direction, loss = jax.shard_map(local, in_specs=(PartitionSpec(), spec), out_specs=PartitionSpec())(
                params, batch
            )
        else:  # one device, or the SVD route (XLA gathers J for it)
            jac, g, loss = self._jacobian_and_gradient(objective, params, batch, 1)
            direction = half_inverse(jac, g, exponent=self.exponent, truncation=self.truncation, route=route)
        _, unravel = ravel_pytree(params)
        updates, state = self.optimizer.update(unravel(direction), state, params)
        return optax.apply_updates(params, updates), state, {"loss": loss, **stats}

    @staticmethod
    def _output_gradient(objective, params, batch):
        """``g = ∂L/∂y`` (rows,) and the batch-mean loss, without J."""
        outputs, flat = batch_output_map(objective.predict, params, batch)
        b = jax.tree.leaves(batch)[0].shape[0]
        loss, g = _loss_and_output_gradient(objective, params, batch, outputs(flat).reshape(b, -1))
        return g, loss

    @staticmethod
    def _jacobian_and_gradient(objective, params, batch, devices):
        """``J`` (rows, P), ``g = ∂L/∂y`` (rows,) and this batch's share of the loss
        ``L = mean over the global batch`` (the batch is 1/devices of it)."""
        jac, y = stacked_jacobian(objective.predict, params, batch)
        loss, g = _loss_and_output_gradient(objective, params, batch, y, devices)
        return jac, g, loss

    def _sharded_direction(self, objective, params, batch, *, devices):
        # Mark the replicated parameters as varying over the devices: differentiating
        # w.r.t. an invariant input would psum the per-device Jacobians (shard_map's
        # transpose of the implicit broadcast), and each device must keep its own rows.
        params = jax.lax.pcast(params, AXIS, to="varying")
        jac, g, loss = self._jacobian_and_gradient(objective, params, batch, devices)
        direction = sharded_gram_route(
            jac, g, AXIS, devices, exponent=self.exponent, truncation=self.truncation
        )
        return direction, jax.lax.psum(loss, AXIS)


def _loss_and_output_gradient(objective, params, batch, y, devices=1):
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


def hig(
    *, lr: float = 1.0, truncation: float = 1e-6, route: str = "auto", blocks: int = 8, lanczos_steps: int = 64
):
    """Half-inverse gradients: −η V Σ^{-1/2} Uᵀ g, applied by SGD (Schnell et al. 2022).

    ``route``: ``auto``/``svd``/``gram`` hold J; ``blockgram`` (exact, ``blocks`` sample
    groups) and ``lanczos`` (approximate, ``lanczos_steps``) never form it."""
    return JacobianPower(-0.5, truncation, route, optax.sgd(lr), blocks, lanczos_steps)


def gn(
    *, lr: float = 1.0, truncation: float = 1e-6, route: str = "auto", blocks: int = 8, lanczos_steps: int = 64
):
    """Gauss–Newton: −η J⁺ g (pseudo-inverse, κ = −1) with the same truncation, by SGD."""
    return JacobianPower(-1.0, truncation, route, optax.sgd(lr), blocks, lanczos_steps)

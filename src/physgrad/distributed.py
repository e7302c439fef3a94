"""Data parallelism over a device mesh, on one host or many, with JAX's own runtime.

One mesh axis, ``"data"``: the mini-batch is split along its sample axis over the mesh's
devices, parameters and optimizer state are replicated. The training step stays one
jitted function; JAX's SPMD partitioner (GSPMD) inserts the collectives (the all-reduce
of a mean gradient, for instance), so every method runs unchanged and gives the
single-device update up to the order of floating-point sums. Methods that need explicit
control over communication read the active mesh with :func:`data_axis_size` and use
``jax.shard_map`` (the distributed half-inverse, :mod:`physgrad.routes.gram`).

Multi-host: :func:`initialize` wraps ``jax.distributed.initialize``; afterwards
``jax.devices()`` lists every process's devices, every process runs the same program on
the same (seed-generated) data, and only process 0 writes files.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .errors import ConfigError, CoordinatorInvalid, DevicesInvalid, DevicesRefused, ProcessesInvalid

AXIS = "data"


def initialize(coordinator: str, num_processes: int, process_id: int) -> None:
    """Join a multi-process run (``jax.distributed.initialize``); call before any JAX work.

    ``coordinator`` is ``HOST:PORT`` of process 0, which listens there. On CPU the
    cross-process collectives use gloo (JAX's default)."""
    if num_processes < 1 or not 0 <= process_id < num_processes:
        raise ProcessesInvalid(process_id, num_processes)
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit():
        raise CoordinatorInvalid(coordinator)
    jax.distributed.initialize(coordinator, num_processes=num_processes, process_id=process_id)


def make_mesh(devices: int | Sequence[jax.Device] | None = 1) -> Mesh | None:  # pyright: ignore[reportInvalidTypeForm]
    """A one-axis ``"data"`` mesh: over the first ``devices`` devices (a number), over the given
    devices (a sequence, e.g. ``jax.devices()[2:6]``), or over every device of every process
    (None); None for a single device (nothing to shard).

    The strings ``"all"``/``"auto"`` and numbers as text (the command line's ``--devices``)
    still work for one release, with a ``DeprecationWarning``."""
    available = jax.device_count()
    if isinstance(devices, str):
        devices = _deprecated_devices(devices)
    if devices is None:
        chosen = jax.devices()
    elif isinstance(devices, int | np.integer):
        n = int(devices)
        if not 1 <= n <= available:
            seen = f"this run sees {available} device(s) ({jax.default_backend()})"
            raise DevicesRefused(n, after=f": {seen}")
        chosen = jax.devices()[:n]
    elif isinstance(devices, Sequence) and devices and all(isinstance(d, jax.Device) for d in devices):
        chosen = list(devices)
    else:
        raise DevicesInvalid(devices, "a number of devices, a sequence of jax devices or None (every device)")
    n = len(chosen)
    if jax.process_count() > 1 and n != available:
        raise DevicesRefused(n, before=f"a multi-process run uses every device ({available}); got ")
    if n == 1:
        return None
    axis_type = (jax.sharding.AxisType.Auto,)
    return jax.make_mesh((n,), (AXIS,), axis_types=axis_type, devices=chosen)


def _deprecated_devices(text: str) -> int | None:
    warnings.warn(
        f"devices={text!r} is deprecated; pass a number, a sequence of jax devices, or None for every device",
        DeprecationWarning,
        stacklevel=3,
    )
    if text in ("all", "auto"):
        return None
    try:
        return int(text)
    except ValueError:
        raise DevicesInvalid(text, "a number or 'all'") from None


def check_batch(batch_size: int, mesh: Mesh | None) -> None:
    """A one-line error unless the batch splits evenly over the mesh."""
    n = mesh_size(mesh)
    if batch_size % n:
        raise ConfigError(f"batch_size {batch_size} does not split over {n} devices; use a multiple of {n}")


def mesh_size(mesh: Mesh | None) -> int:
    return 1 if mesh is None else math.prod(mesh.devices.shape)


def use_mesh(mesh: Mesh | None):
    """``jax.set_mesh(mesh)`` as a context (a no-op without a mesh)."""
    return contextlib.nullcontext() if mesh is None else jax.set_mesh(mesh)


def data_axis_size() -> int:
    """Devices along the ``"data"`` axis of the mesh active while tracing (1 if none)."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or AXIS not in mesh.axis_names:
        return 1
    return mesh.shape[AXIS]


def shard_batch(batch):
    """Inside a jitted step: split every leaf's leading (sample) axis over the mesh."""
    if data_axis_size() == 1:
        return batch
    return jax.lax.with_sharding_constraint(batch, PartitionSpec(AXIS))


def replicated(tree):
    """Inside a jitted step: keep parameters and optimizer state replicated."""
    if data_axis_size() == 1:
        return tree
    return jax.lax.with_sharding_constraint(tree, PartitionSpec())


def replicate(tree, mesh: Mesh | None):
    """Place host values on every device of ``mesh`` (every process passes the same
    values); array leaves only, others pass through."""
    if mesh is None:
        return tree
    sharding = NamedSharding(mesh, PartitionSpec())

    def put(x):
        if not isinstance(x, (jax.Array, np.ndarray)):
            return x
        host = np.asarray(to_host(x))
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(put, tree)


def to_host(tree):
    """Replicated (possibly multi-process) arrays as local NumPy values, for files."""

    def get(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            if not x.is_fully_replicated:  # the caller should have replicated it
                raise ValueError(f"to_host needs a replicated array, got sharding {x.sharding}")
            return np.asarray(x.addressable_data(0))
        return x

    return jax.tree.map(get, tree)


def is_writer() -> bool:
    """Only process 0 writes run directories in a multi-process run."""
    return jax.process_index() == 0


__all__ = [
    "AXIS",
    "check_batch",
    "data_axis_size",
    "initialize",
    "is_writer",
    "make_mesh",
    "replicate",
    "replicated",
    "shard_batch",
    "to_host",
    "use_mesh",
]

"""The memory guard: will a training step fit on the device? Checked before its first step.

A step that cannot fit should be refused in one line, not found out by the operating
system's out-of-memory killer after minutes of data generation and compilation (HIG on
the SIP paper's heat problem would build a 524,288 × 37,249 Jacobian, over 200 GB). Two
estimates, cheapest first:

1. **The method's footprint** (:meth:`physgrad.AbstractMethod.footprint`): the bytes of
   its own large arrays from shapes alone (a half-inverse route's Jacobian and Gram
   matrices; 0 for methods that cannot tell). Instant, no compilation, and it works on
   stand-in batches, so the engine checks it before generating any data.
2. **XLA's figure for the compiled step** (``compiled.memory_analysis()``): outputs and
   temporaries, less outputs aliased to inputs. The engine compiles every stage's step
   ahead of time anyway, so this costs no extra compilation. The step's inputs
   (parameters, optimizer state, training data) are left out: they are already on the
   device when the available memory is read.

The step needs ``max(compiled, footprint)``: XLA's temporaries already hold the route's
arrays, so adding both would count them twice, while the footprint also covers what XLA
leaves out of its analysis (the workspace of library calls such as LAPACK's ``eigh``).
The step fits when that is at most :data:`SAFETY` of the available memory (the device's
limit less what is in use on a GPU; ``MemAvailable`` and the cgroup limit on a CPU host,
whose devices all share the host's memory).

A refused step raises :class:`physgrad.errors.DoesNotFit` (a :class:`physgrad.ConfigError`)
with what would fit: the largest batch size found (halving, then bisecting; confirmed by compiling when the compiled figure
decided), a lighter variant of the method at this batch size (another half-inverse route),
or a device count where the run could use more devices. Before the data exist only the
footprint is known, and what the run will hold besides the step (the dataset, parameters
and optimizer state: ``resident``) is not in use yet, so it is counted against the
available memory: a batch size suggested then passes the footprint check once the data
exist (the compiled check that follows may still lower it). ``memory_guard=False``
(:class:`physgrad.TrainSettings`, ``--set memory_guard=false``) turns the guard off.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from ..errors import DoesNotFit

SAFETY = 0.9  # a step may take this fraction of the available memory (fragmentation, runtime)
_CONFIRMATIONS = 3  # compilations at most to confirm a suggested batch size


# The reportInvalidTypeForm ignores on jax.Device: it aliases a class of the compiled jaxlib,
# which has no stubs, so the checker sees a variable
def available_bytes(device: jax.Device | None = None) -> int | None:  # pyright: ignore[reportInvalidTypeForm]
    """Bytes free on ``device`` (default: the first local device), or None if unknown.

    A GPU/TPU reports its allocator's limit and use (``device.memory_stats()``); a CPU
    device is the host: ``MemAvailable`` from ``/proc/meminfo`` (else ``os.sysconf``),
    capped by a cgroup-v2 memory limit when the process runs in one (containers)."""
    device = device or jax.local_devices()[0]
    assert device is not None  # for the checker, to which jax.Device is unknown
    if device.platform != "cpu":
        try:
            stats = device.memory_stats()
        except Exception:  # noqa: BLE001 — a backend without allocator statistics
            return None
        if not stats or "bytes_limit" not in stats:
            return None
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    return _host_available()


def _host_available() -> int | None:
    free = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                free.append(int(line.split()[1]) * 1024)  # reported in kB
    except (OSError, ValueError, IndexError):
        pass
    if not free:
        try:
            free.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (OSError, ValueError, AttributeError):
            pass
    try:  # a container's own limit, below what the host has free
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            free.append(int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return min(free) if free else None


def compiled_bytes(compiled: Any, arguments: bool = True) -> int | None:
    """Bytes a compiled function needs per device by XLA's ``memory_analysis()``:
    arguments + outputs + temporaries − outputs aliased to (donated) arguments; with
    ``arguments=False`` without the arguments (already in memory). None where the backend
    gives no analysis."""
    try:
        analysis = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 — not every backend implements it
        return None
    analyses = analysis if isinstance(analysis, (list, tuple)) else [analysis]
    sizes = []
    for a in analyses:
        if a is None:
            continue
        size = a.output_size_in_bytes + a.temp_size_in_bytes - a.alias_size_in_bytes
        sizes.append(size + (a.argument_size_in_bytes if arguments else 0))
    return max(sizes) if sizes else None


def stand_in(batch: Any, batch_size: int | None) -> Any:
    """A batch of ``batch_size`` samples shaped like ``batch`` (arrays or
    ``jax.ShapeDtypeStruct``s) for footprints, which read shapes only: broadcast views of
    one zero, so even a huge batch takes no memory. ``batch_size=None`` keeps the shapes."""

    def like(a):
        shape = a.shape if batch_size is None else (batch_size, *a.shape[1:])
        return np.broadcast_to(np.zeros((), a.dtype), shape)

    return jax.tree.map(like, batch)


def check_step_fits(
    method,
    objective,
    params,
    batch,
    *,
    devices: list[jax.Device] | None = None,  # pyright: ignore[reportInvalidTypeForm]  (as in available_bytes)
    compiled: Any = None,
    measure: Callable[[int], int | None] | None = None,
    label: str = "",
    resident: int = 0,
) -> int:
    """Raise :class:`~physgrad.errors.DoesNotFit` (one line, with what would fit) unless one
    step of ``method`` on ``batch`` fits in memory; return the bytes it needs per device.

    Arguments:
        method: an :class:`~physgrad.AbstractMethod` (its ``footprint``, ``footprint_note``,
            ``lighter`` and ``check_batch_size``).
        objective, params: the problem's pieces and the parameters (arrays or
            ``jax.ShapeDtypeStruct``s).
        batch: the global batch, or a :func:`stand_in` of it.
        devices: the devices the batch is split over (default: the first device).
        compiled: the compiled step, if there is one: its XLA memory analysis joins the
            footprint. Without it only the footprint is checked.
        measure: ``measure(batch_size)`` compiles the step at another batch size and
            returns its :func:`compiled_bytes` without arguments; used to confirm a
            suggested batch size when the compiled figure decided.
        label: the method's name in the message.
        resident: bytes per device that the run will hold while the step runs but that
            are not in memory yet (before the data exist: the dataset, parameters and
            optimizer state, :func:`tree_bytes`); counted against the available memory.
    """
    devices = devices or [jax.local_devices()[0]]
    mine = [d for d in devices if d.process_index == jax.process_index()] or devices
    reported = [available_bytes(d) for d in mine]
    free = [f for f in reported if f is not None]
    if len(free) < len(reported):
        return 0  # this backend does not say: no check
    # CPU devices are one host's memory: every local device's share lands in the same pool.
    shared = len(mine) if mine[0].platform == "cpu" else 1
    budget = SAFETY * min(free) - resident * shared
    n, b = len(devices), _batch_size(batch)
    where = "the host" if mine[0].platform == "cpu" else "the device"
    step = compiled_bytes(compiled, arguments=False) if compiled is not None else None
    footprint = method.footprint(objective, params, batch, n)
    need = max(footprint, step or 0)
    if budget <= 0:  # the data and parameters alone do not fit: no batch size, variant or device count helps
        raise DoesNotFit(f"{label or 'the'} step needs at least ~{_size((need + resident) * shared)}, "
                         f"~{_size(resident * shared)} of it for the data and parameters alone, but {where} has "
                         f"{_size(min(free))} available; reduce the data (n_train, n_test) (memory_guard=false "
                         "skips this check)")  # fmt: skip
    if need * shared <= budget:
        return need

    def fits(bytes_per_device):
        return bytes_per_device * shared <= budget

    def footprint_at(size):
        return method.footprint(objective, params, _first(batch, size), n)

    # The compiled step at another batch size, by a line through the last two compiled
    # figures (through zero while there is one): confirmations refine it like a secant.
    points = [] if step is None else [(b, step)]

    def batch_need(size):
        if not points:
            return footprint_at(size)
        (b1, n1), (b2, n2) = points[-2:] if len(points) > 1 else ((0, 0), points[0])
        return max(footprint_at(size), n2 + (n2 - n1) / (b2 - b1) * (size - b2))

    suggestions = []
    size = _largest_batch(method, b, n, lambda s: fits(batch_need(s)))
    if measure is not None and step is not None:  # the compiled figure counted: confirm by compiling
        for _ in range(_CONFIRMATIONS):
            measured = None if size is None else measure(size)
            if size is None or measured is None or fits(max(footprint_at(size), measured)):
                break
            points.append((size, measured))
            size = _largest_batch(method, size, n, lambda s: fits(batch_need(s)))
        else:
            size = None  # not confirmed
    if size is not None:
        suggestions.append(f"batch_size={size}")
    rest = max((step or 0) - footprint, 0)  # what the compiled step holds besides the method's arrays
    for variant in method.lighter(b):
        if _accepts(variant, b, n) and fits(variant.footprint(objective, params, batch, n) + rest):
            suggestions.append(_difference(method, variant))
            break
    more_devices = None  # a device count that would fit, written by the error in its reader's words
    if mine[0].platform != "cpu":  # more accelerators add memory; more CPU devices do not
        for more in range(n + 1, jax.device_count() + 1):
            if b % more == 0 and fits(max(method.footprint(objective, params, batch, more), (step or 0) * n / more)):
                more_devices = more
                break
    note = method.footprint_note(objective, params, batch)
    if step is not None and step > footprint:
        note = "compiled step" + (f"; {note}" if note else "")
    if suggestions or more_devices is not None:
        fit = f"would fit: {' or '.join(suggestions)}" + (" or " if suggestions and more_devices is not None else "")
    else:
        fit = "found no batch size, variant or device count that fits"
    held = f", {_size(resident * shared)} of it for the data and parameters" if resident else ""
    message = (
        f"{label or 'the'} step needs ~{_size(need * shared)}" + (f" ({note})" if note else "")
        + f" but {where} has {_size(min(free))} available{held}; {fit}"
    )  # fmt: skip
    guard = " (memory_guard=false skips this check)"
    if more_devices is None:
        raise DoesNotFit(message + guard)
    raise DoesNotFit(message, more_devices, guard)


def tree_bytes(tree: Any) -> int:
    """Bytes of a pytree's arrays (or ``jax.ShapeDtypeStruct``s): its size in memory."""
    return sum(int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree) if hasattr(x, "dtype"))


def _batch_size(batch) -> int:
    return jax.tree.leaves(batch)[0].shape[0]


def _first(batch, size: int):
    return jax.tree.map(lambda a: a[:size], batch)


def _difference(before: Any, after: Any) -> str:
    """What a variant changes, as ``field=value`` in the objects' own field names: a field
    holding an object of another class by that class's lower-case name and its fields that
    differ from their defaults (a rule whose ``route`` became ``BlockGram(4)`` reads
    as the field, ``blockgram`` and ``blocks=4``); objects of one class are compared field
    by field."""
    parts = []
    for field in dataclasses.fields(after):
        old, new = getattr(before, field.name), getattr(after, field.name)
        if old is new or (type(old) is type(new) and eqx.tree_equal(old, new) is True):
            continue
        if type(old) is type(new) and dataclasses.is_dataclass(new):
            parts.append(_difference(old, new))
        elif dataclasses.is_dataclass(new):
            own = [f"{f.name}={getattr(new, f.name)}" for f in dataclasses.fields(new)
                   if f.default is dataclasses.MISSING or getattr(new, f.name) != f.default]  # fmt: skip
            parts.append(" ".join([f"{field.name}={type(new).__name__.lower()}", *own]))
        else:
            parts.append(f"{field.name}={new}")
    return " ".join(parts)


def _accepts(method, batch_size: int, devices: int) -> bool:
    if batch_size % devices:
        return False
    try:
        method.check_batch_size(batch_size)
    except ValueError:
        return False
    return True


def _largest_batch(method, below: int, devices: int, fits: Callable[[int], bool]) -> int | None:
    """The largest valid batch size under ``below`` that ``fits``: halve until one fits,
    then bisect between it and the last that did not (assuming need grows with the batch
    there); every size returned was checked."""

    def largest_valid(at_most: int) -> int | None:  # usually the first size tried: no list of every size
        return next((s for s in range(min(at_most, below - 1), 0, -1) if _accepts(method, s, devices)), None)

    # halving: the largest valid size at or below below/2, below/4, ...
    hi, target = None, below
    while True:
        target //= 2
        lo = largest_valid(target)
        if lo is None:
            return None
        if fits(lo):
            break
        hi = lo
    # bisect on the integers between lo (fits) and hi (does not, or ``below``), each probe
    # stepped down to a valid size: O(log) probes however large the batch
    left, right = lo, hi or below
    while right - left > 1:
        mid = (left + right) // 2
        size = largest_valid(mid)
        if size is None or size <= lo:  # no valid size in (lo, mid]: look above
            left = mid
        elif fits(size):
            lo, left = size, mid
        else:  # need grows with the batch: nothing from size up fits
            right = size
    return lo


def _size(n: float) -> str:
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{int(n)} B"

"""Compiled programs shared by the runs of one process.

The runs of a study differ in their seed, that is in their data and initial network, which
are the *arguments* of the training step, not its program. So a study's second seed of a
method need not trace and compile that method's step again: :class:`ProgramCache` keeps the
compiled step (and the jitted evaluation) under a key of everything the program depends on:

- the problem instance (its settings: problems are Equinox modules, equal when their
  settings are equal);
- the network's static part (activation functions, layer structure; not its weights);
- the method object (a method holds optax closures, so two separately built methods are
  never equal: the command line builds each configured method once per process,
  :func:`physgrad.harness.train.phases_of`, and a library user who passes the same method object
  to several ``fit`` calls shares its program the same way);
- the batch size, the device mesh, and the shape, dtype and sharding of every argument.

Anything that cannot be hashed (say a problem that holds an array) gives no key, and the
program is compiled afresh, exactly as without the cache.

Across processes, JAX's persistent compilation cache does the same job on disk:
:func:`use_compilation_cache` (the command line's ``--compilation-cache DIR``).

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

import jax
import numpy as np


def abstract_key(tree: Any) -> Hashable:
    """The structure of ``tree`` and the shape, dtype and sharding of each array leaf
    (other leaves by value); raises TypeError if a leaf cannot be hashed."""
    leaves, treedef = jax.tree.flatten(tree)

    def leaf(x):
        if isinstance(x, (jax.Array, np.ndarray)):
            return (tuple(x.shape), str(x.dtype), getattr(x, "sharding", None))
        hash(x)
        return x

    return treedef, tuple(leaf(x) for x in leaves)


def static_key(tree: Any) -> Hashable:
    """The structure and non-array leaves of ``tree`` (a network's static part); raises
    TypeError if it holds something unhashable (an array kept out of the parameters)."""
    leaves, treedef = jax.tree.flatten(tree)
    for x in leaves:
        if isinstance(x, (jax.Array, np.ndarray)):
            raise TypeError("an array in the static part")
        hash(x)
    hash(treedef)
    return treedef, tuple(leaves)


class ProgramCache:
    """A small least-recently-used map from keys to what they build: compiled programs here,
    the command line's method objects in :func:`physgrad.harness.train.phases_of`.

    ``get(key, build)`` returns the program stored under ``key``, or calls ``build()``,
    stores and returns its result; a ``key`` of None (nothing hashable to key on) always
    builds. ``hits`` and ``misses`` count lookups (for tests and ``summary.json``)."""

    def __init__(self, size: int = 32):
        self.size = size
        self._programs: collections.OrderedDict[Hashable, Any] = collections.OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def get(self, key: Hashable | None, build: Callable[[], Any]) -> tuple[Any, bool]:
        """``(program, hit)``."""
        if key is not None:
            with self._lock:
                try:
                    program = self._programs[key]
                except (KeyError, TypeError):  # TypeError: a key part whose __eq__ cannot decide
                    pass
                else:
                    self._programs.move_to_end(key)
                    self.hits += 1
                    return program, True
        program = build()
        with self._lock:
            self.misses += 1
            if key is not None:
                self._programs[key] = program
                while len(self._programs) > self.size:
                    self._programs.popitem(last=False)
        return program, False

    def clear(self) -> None:
        with self._lock:
            self._programs.clear()
            self.hits = self.misses = 0


def key(*parts: Any, static: Any = None, arguments: Any = None) -> Hashable | None:
    """``parts``, the structure of ``static`` (a network's non-array part, :func:`static_key`)
    and the abstract values of ``arguments`` (:func:`abstract_key`) as one key; None if
    any of them cannot be hashed (the program is then compiled afresh)."""
    try:
        whole = (*parts, static_key(static), abstract_key(arguments))
        hash(whole)
    except TypeError:
        return None
    return whole


# The process's programs: training steps (compiled executables) and evaluations (jitted
# functions, whose own cache then handles each split's shapes).
STEPS = ProgramCache()
EVALUATIONS = ProgramCache()


def use_compilation_cache(directory: str | Path, min_compile_seconds: float = 0.5) -> None:
    """Turn on JAX's persistent compilation cache in ``directory`` for this process, so a
    repeated study loads its compiled steps from disk instead of compiling them again.

    This changes JAX's global configuration (``jax_compilation_cache_dir``), so physgrad
    never calls it on its own: the command line does when given ``--compilation-cache`` (or
    ``PHYSGRAD_COMPILATION_CACHE``), a script may call it once at its start. Programs that
    compile faster than ``min_compile_seconds`` are not stored."""
    path = Path(directory).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

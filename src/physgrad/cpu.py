"""CPU thread pools: a scoped limit for a user's own loop, and the command line's process setting.

A Jacobian method's float64 ``eigh`` runs in jaxlib's CPU LAPACK kernels, which call
SciPy's OpenBLAS. OpenBLAS starts one thread per core and spins them on every call; when
other processes hold the cores, those threads wait for each other and the step collapses
(on a 2-core machine at load ≈ 4 the same compiled HIG step took 16–171 ms with OpenBLAS's
default threads and 3.2 ms with one thread; ``docs/performance.md``, "Threads under load").

Importing this module (or physgrad) changes nothing: no environment variable, no thread
pool. Three explicit levels:

* :func:`threads` — ``with physgrad.threads(1): ...`` around a user's own training loop. It
  limits the BLAS/LAPACK and OpenMP pools of the libraries loaded in this process
  (``threadpoolctl.threadpool_limits``; SciPy's LAPACK is loaded first, so the ``eigh``
  that jaxlib runs on it is covered) and restores them on exit. It cannot size XLA's own
  intra-op pool (its matrix products and convolutions on CPU): XLA sizes that once, when
  JAX's backend starts.
* :func:`start_xla` — ``physgrad.cpu.start_xla(1)`` at the top of a script, before the
  first JAX computation: starts JAX's backend with XLA's pool sized to that many threads
  (it sizes the pool from the process's CPU affinity; the affinity is narrowed for the
  start and given back to every thread after).
* :func:`process_threads` — what physgrad's own processes do (``physgrad --threads N``,
  default 1 for ``train``, ``compare``, ``bench`` and ``demo``, and each Dask worker): the
  same limit, the environment variables that libraries loaded later read
  (``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``) and, where JAX's
  backend has not started yet, :func:`start_xla`. Everything but XLA's pool (fixed once
  the backend starts) is restored on exit.

:func:`report` is what a run records in ``env.json`` under ``threads``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from typing import Any

# The variables that OpenBLAS, OpenMP runtimes and MKL read when they load.
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

# The process setting in force (None: none; physgrad.cpu.process_threads sets and clears it).
_process_setting: dict[str, Any] | None = None


def _check(n: int) -> int:
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"a thread count must be a positive integer, got {n!r}")
    return n


def _load_lapack() -> None:
    """Load SciPy's LAPACK (and so its OpenBLAS) now: jaxlib loads it at the first LAPACK
    call, and a library loaded after a limit is set would keep its own default."""
    import scipy.linalg.cython_lapack  # noqa: F401


@contextlib.contextmanager
def threads(n: int) -> Iterator[None]:
    """Limit the BLAS/LAPACK and OpenMP thread pools of this process to ``n`` threads
    inside the block, and restore them on exit (``threadpoolctl.threadpool_limits``).

    Covers jaxlib's CPU LAPACK kernels (the Jacobian methods' float64 ``eigh``: they run on
    SciPy's OpenBLAS, loaded here first), NumPy's OpenBLAS and any OpenMP runtime loaded.
    Does not cover XLA's own intra-op pool (matrix products, convolutions), which XLA
    sizes once when JAX's CPU backend starts (:func:`start_xla` before the first JAX
    computation; the ``physgrad`` command line does this itself, :func:`process_threads`)::

        with physgrad.threads(1):
            for batch in batches:
                params, opt_state = step(params, opt_state, batch)
    """
    from threadpoolctl import threadpool_limits

    _check(n)
    _load_lapack()
    with threadpool_limits(limits=n):
        yield


def backend_started() -> bool:
    """Whether JAX's backends have started (after which ``XLA_FLAGS`` no longer applies)."""
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without the query: assume the worst
        return True


def xla_thread_flags(n: int) -> str:
    """The ``XLA_FLAGS`` words for ``n`` threads: for one, ``--xla_cpu_multi_thread_eigen=false``
    (meant to run XLA's Eigen kernels on the calling thread; with jaxlib 0.10 the intra-op
    pool still shares the work, measured per thread: :func:`start_xla` is what sizes it);
    for more, none (``intra_op_parallelism_threads=N``, a TensorFlow setting often quoted
    for this, is no XLA flag: XLA skips it without a word)."""
    return "--xla_cpu_multi_thread_eigen=false" if _check(n) == 1 else ""


def _tasks() -> set[int]:
    try:
        return {int(t) for t in os.listdir("/proc/self/task")}
    except OSError:
        return set()


def start_xla(n: int) -> str:
    """Start JAX's backends with XLA's CPU intra-op thread pool sized to ``n`` threads, and
    say what was done (a line for ``env.json``). Call it before the first JAX computation.

    XLA sizes that pool once, when JAX's backend starts, from the number of CPUs the
    process may run on (its affinity mask; no flag or option of jaxlib 0.10 sets the
    count). So this narrows the calling thread's mask to ``n`` of its CPUs, starts the
    backend (``jax.devices()``), and gives every thread started meanwhile, and the calling
    thread, the whole mask back: the pool has ``n`` threads that the kernel still moves
    over every CPU the process had. (Pinning the process instead, ``taskset -c K``, sizes
    the pool too but ties it to CPU K, which a neighbour may be using.) Measured per thread
    on a 1500² matrix product (``docs/performance.md``, "Threads under load"): after
    ``start_xla(1)`` one thread does all the work; with the default pool, or with
    ``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false``, three.

    It starts JAX's backend, so a multi-process run joins first
    (:func:`physgrad.distributed.initialize`: ``jax.distributed`` refuses once the backend
    has started); the command line does. Linux only (``os.sched_setaffinity``); elsewhere,
    or with fewer than ``n`` CPUs in the mask, the backend starts with XLA's default.
    Raises ``RuntimeError`` if JAX's backend has started already: XLA's pool cannot change
    then::

        import physgrad
        physgrad.cpu.start_xla(1)  # first, before anything computes with JAX
    """
    _check(n)
    if backend_started():
        raise RuntimeError(
            "JAX's backend has started already, so XLA's thread pool is fixed; call "
            "physgrad.cpu.start_xla(n) before the first JAX computation (at the top of the script)"
        )
    import jax

    getter, setter = getattr(os, "sched_getaffinity", None), getattr(os, "sched_setaffinity", None)
    mask = getter(0) if getter is not None else set()
    if setter is None or len(mask) <= n:
        jax.devices()
        return f"XLA default ({len(mask) or os.cpu_count()} CPUs usable: nothing to narrow)"
    before = _tasks()
    setter(0, set(sorted(mask)[:n]))
    try:
        jax.devices()
    finally:
        setter(0, mask)
        for task in _tasks() - before:  # the backend's threads, started on the narrowed mask
            try:
                setter(task, mask)
            except OSError:  # a thread that has ended meanwhile
                pass
    return f"{n} (XLA's pool sized on {n} of {len(mask)} CPUs, then given all {len(mask)} back)"


@contextlib.contextmanager
def process_threads(n: int | None) -> Iterator[dict[str, Any]]:
    """The command line's thread setting for the duration of a command; yields what it did
    (also :func:`report`'s ``setting``). ``n`` None leaves every pool at its default.

    Sets :data:`THREAD_VARIABLES` (for libraries loaded later), starts JAX's backend with
    XLA's pool sized to ``n`` if it has not started (:func:`start_xla`), and limits the
    pools already loaded (:func:`threads`). On exit the variables and the loaded pools are
    restored; XLA's pool, sized when its backend started, stays for the process."""
    global _process_setting
    if n is None:
        setting = {"requested": None, "blas": "library default", "xla": "XLA default"}
        _process_setting, previous = setting, _process_setting
        try:
            yield setting
        finally:
            _process_setting = previous
        return
    _check(n)
    saved = {k: os.environ.get(k) for k in (*THREAD_VARIABLES, "XLA_FLAGS")}
    flags = saved["XLA_FLAGS"] or ""
    if backend_started():
        xla = "not limited: JAX's backend had started before the setting"
    else:
        if n == 1 and "multi_thread_eigen" not in flags:  # for an older XLA that reads it
            os.environ["XLA_FLAGS"] = f"{flags} {xla_thread_flags(n)}".strip()
        xla = start_xla(n)
    setting = {"requested": n, "blas": n, "xla": xla}
    for k in THREAD_VARIABLES:
        os.environ[k] = str(n)
    _process_setting, previous = setting, _process_setting
    try:
        with threads(n):
            yield setting
    finally:
        _process_setting = previous
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def report() -> dict[str, Any]:
    """This process's thread pools as ``env.json`` records them: the command line's
    ``setting`` (None outside it), each loaded BLAS/OpenMP pool's size
    (``threadpoolctl.threadpool_info``), the thread variables and ``XLA_FLAGS``."""
    try:
        from threadpoolctl import threadpool_info

        pools = [
            {k: info.get(k) for k in ("internal_api", "prefix", "num_threads", "version", "threading_layer")}
            for info in threadpool_info()
        ]
    except Exception as e:  # noqa: BLE001 — a record must never stop a run
        pools = [{"error": f"{type(e).__name__}: {e}"}]
    return {
        "setting": _process_setting,
        "pools": pools,
        "environment": {k: os.environ.get(k) for k in (*THREAD_VARIABLES, "XLA_FLAGS")},
        "cpu_count": os.cpu_count(),
    }

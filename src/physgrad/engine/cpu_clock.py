"""The CPU seconds of a run's own work: the thread that steps it and XLA's, not its host's.

A chunk of training steps is host work on the thread that calls it (dispatch, read-back)
and XLA's compute on XLA's own native threads. ``time.process_time`` counts every thread of
the process, and so also charged a run with the CPU of whatever else its process hosts in
the meantime: a Dask worker's event loop (heartbeats, its tick and memory monitors; about
23 ms of CPU per wall-clock second in an idle worker of physgrad's ``LocalCluster``), or the
scheduler's and nannies' loop in the process that started the cluster (about 50 ms per
second) when it calibrates. That CPU grows with wall-clock time, not with steps, so the more
load stretched a step the more it added to it: on ``hig_toy`` in two workers under load,
HIG's in-run CPU step read 1.38x its calibrated one, against 1.09x in one process.

:func:`run_cpu_time` is the process's CPU seconds less those of its other **Python**
threads (``threading.enumerate()``, the calling thread excepted): the host's loops, a
progress bar's refresh, a checkpoint writer are Python threads; XLA's compute threads are
native threads Python does not list, so they stay counted. A thread that native code lends
to a Python callback (``threading._DummyThread``) is not excluded either: it may be XLA's.

Each reading keeps, per calling thread, a running total: the process's CPU since the last
reading less each other Python thread's since then (a thread new since then: all of its
CPU; a thread that ended: its last slice stays counted, as ``process_time`` counted it).
So a thread that starts or ends between two readings cannot move the total by its whole
lifetime's CPU, as a plain sum over the living threads would. Only differences between
readings of one thread mean anything.

A thread's CPU is read from Linux's per-thread CPU clock (``clock_gettime`` of the clock id
the kernel derives from the thread's id, the encoding glibc's ``pthread_getcpuclockid``
uses; nanoseconds, one system call, an error once the thread has ended). Elsewhere
(macOS, Windows) :func:`run_cpu_time` is ``time.process_time``.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import sys
import threading
import time

# The kernel's clock id of thread TID's CPU time (CPUCLOCK_PERTHREAD_MASK | CPUCLOCK_SCHED
# over the bit-inverted id: include/linux/posix-timers.h, glibc's MAKE_THREAD_CPUCLOCK).
_PER_THREAD_SCHED = 0b110
PER_THREAD_CLOCKS = sys.platform.startswith("linux") and hasattr(time, "clock_gettime")

_state = threading.local()


def thread_seconds(native_id: int) -> float | None:
    """CPU seconds of this process's thread ``native_id`` (``threading.get_native_id``),
    or None where it has ended (or the platform has no per-thread clocks)."""
    if not PER_THREAD_CLOCKS:
        return None
    try:
        return time.clock_gettime(((~native_id) << 3) | _PER_THREAD_SCHED)
    except OSError:  # EINVAL: no such thread in this process (it has ended)
        return None


def _other_python_threads() -> dict[int, float]:
    """CPU seconds of each living Python thread of this process but the calling one."""
    me = threading.get_ident()
    seconds = {}
    for t in threading.enumerate():
        if t.ident == me or t.native_id is None or isinstance(t, threading._DummyThread):  # pyright: ignore[reportAttributeAccessIssue]
            continue
        s = thread_seconds(t.native_id)
        if s is not None:
            seconds[t.native_id] = s
    return seconds


def run_cpu_time() -> float:
    """Seconds of CPU that the calling thread's work took: the process's CPU time less its
    other Python threads' (see the module docstring), as a running total per calling thread;
    ``time.process_time()`` where the platform has no per-thread clocks. Take differences."""
    process = time.process_time()
    if not PER_THREAD_CLOCKS:
        return process
    threads = _other_python_threads()
    last = getattr(_state, "last", None)
    if last is None:
        _state.total = process - sum(threads.values())
    else:
        last_process, last_threads = last
        others = 0.0
        for tid, s in threads.items():
            before = last_threads.get(tid, 0.0)
            others += s - before if s >= before else s  # smaller: a new thread that reuses an ended one's id
        _state.total += process - last_process - others
    _state.last = (process, threads)
    return _state.total


__all__ = ["PER_THREAD_CLOCKS", "run_cpu_time", "thread_seconds"]

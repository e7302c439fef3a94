"""The run's CPU clock (engine/cpu_clock.py): the process's CPU seconds less its other Python
threads', checked against the kernel's own clocks (time.thread_time, time.process_time) with
threads that spin for a known CPU time."""

from __future__ import annotations

import threading
import time

import pytest

from physgrad.engine import cpu_clock
from physgrad.engine.cpu_clock import run_cpu_time, thread_seconds

pytestmark = pytest.mark.skipif(not cpu_clock.PER_THREAD_CLOCKS, reason="per-thread CPU clocks are Linux's")

SPIN = 0.2  # CPU seconds a spinning thread burns: far above the clocks' noise, short on a loaded machine
TOLERANCE = 0.05  # the calling thread's own bookkeeping between readings, and a loaded scheduler's slack


def _spin(seconds: float) -> None:
    """Burn ``seconds`` of this thread's CPU (time.thread_time, whatever the load)."""
    t0 = time.thread_time()
    while time.thread_time() - t0 < seconds:
        pass


def _spinner(seconds: float, hold: threading.Event | None = None):
    """A Python thread that spins ``seconds`` of CPU, signals ``done``, then waits on ``hold``."""
    done = threading.Event()

    def body():
        _spin(seconds)
        done.set()
        if hold is not None:
            hold.wait(30)

    thread = threading.Thread(target=body, daemon=True)
    return thread, done


def test_a_threads_clock_is_the_kernels_clock_of_that_thread():
    """thread_seconds of the calling thread's id agrees with time.thread_time; an ended
    thread's id reads None (the kernel refuses a clock of no thread of this process) once the
    kernel has let the thread go."""
    _spin(0.05)
    before, mine, after = time.thread_time(), thread_seconds(threading.get_native_id()), time.thread_time()
    assert mine is not None and before <= mine <= after
    thread, _ = _spinner(0.01)
    thread.start()
    thread.join()  # Python's side of the thread is done; the kernel's ends a moment later
    assert thread.native_id is not None
    deadline = time.monotonic() + 10
    while thread_seconds(thread.native_id) is not None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert thread_seconds(thread.native_id) is None


def test_another_python_threads_cpu_is_not_the_runs():
    """While the calling thread waits, another Python thread spins SPIN seconds: the
    process clock counts them, the run's clock does not."""
    hold = threading.Event()
    thread, done = _spinner(SPIN, hold)
    cpu0, process0 = run_cpu_time(), time.process_time()
    thread.start()
    assert done.wait(60)
    cpu, process = run_cpu_time() - cpu0, time.process_time() - process0
    hold.set()
    thread.join()
    assert process >= SPIN * 0.95
    assert abs(cpu) < TOLERANCE


def test_the_calling_threads_own_cpu_is_counted_beside_an_idle_thread():
    hold = threading.Event()
    thread, _ = _spinner(0.0, hold)
    thread.start()
    cpu0, own0 = run_cpu_time(), time.thread_time()
    _spin(SPIN)
    cpu, own = run_cpu_time() - cpu0, time.thread_time() - own0
    hold.set()
    thread.join()
    assert cpu == pytest.approx(own, abs=TOLERANCE)


def test_threads_that_start_or_end_between_readings_move_the_total_by_their_slice_only():
    """A thread that spun before the first reading and ends before the second leaves the
    difference alone (a sum over the living threads would drop by its SPIN seconds); a
    thread new since the first reading has all its CPU taken out."""
    hold = threading.Event()
    old, old_done = _spinner(SPIN, hold)
    old.start()
    assert old_done.wait(60)
    cpu0 = run_cpu_time()
    hold.set()
    old.join()  # ended between the readings, after its spin
    new_hold = threading.Event()
    new, new_done = _spinner(SPIN, new_hold)
    new.start()
    assert new_done.wait(60)
    cpu = run_cpu_time() - cpu0
    new_hold.set()
    new.join()
    assert abs(cpu) < TOLERANCE


def test_readings_are_kept_per_calling_thread():
    """Two threads that spin at once, each between its own two readings, each see their own
    CPU: the readings of one do not enter the other's total (both live until both have read:
    an ended thread's last slice would stay counted)."""
    results = {}
    read = threading.Barrier(2)

    def worker(name, seconds, ready, go):
        start = run_cpu_time()
        ready.set()
        go.wait(30)
        _spin(seconds)
        results[name] = run_cpu_time() - start
        read.wait(30)

    ready = [threading.Event(), threading.Event()]
    go = threading.Event()
    threads = [threading.Thread(target=worker, args=(n, s, r, go)) for n, s, r in zip("ab", (SPIN, SPIN / 2), ready)]
    for t in threads:
        t.start()
    for r in ready:
        assert r.wait(30)
    go.set()
    for t in threads:
        t.join()
    assert results["a"] == pytest.approx(SPIN, abs=TOLERANCE)
    assert results["b"] == pytest.approx(SPIN / 2, abs=TOLERANCE)


def test_xlas_work_is_counted_whichever_thread_does_it():
    """A jitted computation's CPU, on the calling thread or XLA's native ones, is the
    process's: with no other Python thread busy the two clocks agree."""
    import jax
    import jax.numpy as jnp

    x = jnp.ones((400, 400))
    f = jax.jit(lambda a: jnp.linalg.matrix_power(a / 400.0, 64))
    f(x).block_until_ready()
    cpu0, process0 = run_cpu_time(), time.process_time()
    t0 = time.process_time()
    while time.process_time() - t0 < SPIN:
        f(x).block_until_ready()
    cpu, process = run_cpu_time() - cpu0, time.process_time() - process0
    assert cpu == pytest.approx(process, abs=TOLERANCE)

"""Thread pools (physgrad.cpu): the scoped opt-in limits and restores the BLAS/LAPACK pools,
start_xla sizes XLA's intra-op pool when it comes before JAX's backend starts, the command
line's process setting does both and restores what it can, and every run records its
threads in env.json. Importing physgrad changes nothing
(tests/test_side_effects.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import pytest
from threadpoolctl import threadpool_info

import physgrad
from physgrad import cpu
from physgrad.harness.cli import main


def blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_threads_limits_the_blas_pools_in_the_block_and_restores_them():
    physgrad.threads  # noqa: B018 — the public name
    with physgrad.threads(1):
        before = blas_threads()  # SciPy's OpenBLAS (jaxlib's LAPACK) is loaded by now
    assert any(p["prefix"] == "libscipy_openblas" for p in threadpool_info())
    original = blas_threads()
    with physgrad.threads(2):
        assert set(blas_threads()) == {2}
        with physgrad.threads(1):
            assert set(blas_threads()) == {1}
        assert set(blas_threads()) == {2}
    assert blas_threads() == original and set(before) == {1}
    with pytest.raises(ValueError, match="positive integer"):
        with physgrad.threads(0):
            pass


# One thread's CPU ticks per thread of a fresh interpreter over three 1200² float64 products
# (utime + stime from /proc), and whether every thread may run on every CPU again.
_POOL_PROBE = """
import os, sys
import physgrad
mask = os.sched_getaffinity(0)
if sys.argv[1] == "1":
    print(physgrad.cpu.start_xla(1), file=sys.stderr)
import jax, jax.numpy as jnp
def ticks():
    out = {}
    for t in os.listdir("/proc/self/task"):
        fields = open(f"/proc/self/task/{t}/stat").read().rsplit(")", 1)[1].split()
        out[t] = int(fields[11]) + int(fields[12])
    return out
a = jnp.ones((1200, 1200))
product = jax.jit(lambda a: (a @ a) @ a).lower(a).compile()
product(a).block_until_ready()
before = ticks()
for _ in range(3):
    product(a).block_until_ready()
after = ticks()
busy = sorted((after[t] - before.get(t, 0) for t in after), reverse=True)
print(busy[0], busy[1], all(os.sched_getaffinity(int(t)) == mask for t in after))
"""


@pytest.mark.costly("XLA sizes its pool when its backend starts: two fresh interpreters")
@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2, reason="Linux, 2+ CPUs")
def test_start_xla_sizes_the_intra_op_pool_and_gives_the_cpus_back():
    """XLA's default pool spreads a large product over several threads; after
    ``start_xla(1)`` one thread does (nearly) all of it, and every thread may again run on
    every CPU of the process (the pool is sized, not pinned)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"

    def probe(sized: bool) -> tuple[int, int, bool]:
        result = subprocess.run([sys.executable, "-c", _POOL_PROBE, "1" if sized else "0"], capture_output=True,
                                text=True, env=env, timeout=300)  # fmt: skip
        assert result.returncode == 0, result.stderr[-3000:]
        first, second, unpinned = result.stdout.split()
        return int(first), int(second), unpinned == "True"

    first, second, unpinned = probe(sized=True)
    assert unpinned and second <= 0.1 * first  # one worker thread: the rest is bookkeeping
    first, second, unpinned = probe(sized=False)
    assert unpinned and second >= 0.15 * first  # the default pool shares the work
    jax.numpy.zeros(1).block_until_ready()  # this test process has started JAX's backend
    with pytest.raises(RuntimeError, match="before the first JAX computation"):
        cpu.start_xla(1)


def test_process_threads_sets_and_restores_the_variables(monkeypatch):
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "7")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    flags = os.environ.get("XLA_FLAGS")
    with cpu.process_threads(2) as setting:
        assert os.environ["OPENBLAS_NUM_THREADS"] == os.environ["MKL_NUM_THREADS"] == "2"
        assert setting["requested"] == 2 and set(blas_threads()) == {2}
        # the test session started JAX with its own thread flags (conftest.py): XLA keeps them
        assert setting["xla"] in ("the caller's XLA_FLAGS", "not limited: JAX's backend had started before the setting")
        assert cpu.report()["setting"] == setting
    assert os.environ["OPENBLAS_NUM_THREADS"] == "7" and "MKL_NUM_THREADS" not in os.environ
    assert os.environ.get("XLA_FLAGS") == flags and cpu.report()["setting"] is None
    with cpu.process_threads(None) as setting:
        assert setting["requested"] is None and os.environ["OPENBLAS_NUM_THREADS"] == "7"


@pytest.mark.costly("XLA's flags act only before its backend starts: a fresh interpreter runs the command line")
def test_the_command_line_sizes_xla_before_its_backend_starts(tmp_path):
    """In a fresh interpreter without thread variables: ``--threads 1`` (the default) sets
    XLA_FLAGS before JAX's backend starts (XLA accepts the flags: the run finishes), and the
    run's env.json records the setting and one thread per BLAS pool."""
    env = {k: v for k, v in os.environ.items() if k not in (*cpu.THREAD_VARIABLES, "XLA_FLAGS", "PHYSGRAD_THREADS")}
    env["JAX_PLATFORMS"] = "cpu"
    cache = os.environ.get("PHYSGRAD_TEST_XLA_CACHE", os.path.expanduser("~/.cache/physgrad/test-xla"))
    if cache:  # the suite's persistent compilation cache (conftest.py), also for this interpreter's programs
        env.update(JAX_COMPILATION_CACHE_DIR=cache, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                   JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")  # fmt: skip
    # 64 test cases, not 1024: writing test_cases.json compiles an unstack of them (~1 s of CPU at
    # 1024 with XLA's default optimisation, which this interpreter runs with)
    code = textwrap.dedent(f"""
        import os
        from physgrad.harness.cli import main
        assert main(["train", "hig_toy", "--method", "adam", "--steps", "2", "--quiet", "--set", "batch_size=64",
                     "--set", "n_test=64", "--out", {str(tmp_path / "run")!r}]) == 0
        assert "XLA_FLAGS" not in os.environ and "OPENBLAS_NUM_THREADS" not in os.environ  # restored
    """)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    threads = json.loads((tmp_path / "run" / "env.json").read_text())["threads"]
    assert threads["setting"]["requested"] == threads["setting"]["blas"] == 1
    assert threads["setting"]["xla"].startswith(("1 (XLA's pool sized on 1 of", "XLA default (1 CPUs usable"))
    assert threads["environment"]["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=false"
    assert threads["environment"]["OPENBLAS_NUM_THREADS"] == "1"
    pools = [p for p in threads["pools"] if p["internal_api"] == "openblas"]
    assert pools and all(p["num_threads"] == 1 for p in pools)


def test_threads_flag_is_recorded_and_checked(tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["train", "hig_toy", "--method", "adam", "--steps", "2", "--quiet", "--set", "batch_size=64"]
    assert main([*argv, "--threads", "2", "--out", str(out)]) == 0
    assert json.loads((out / "env.json").read_text())["threads"]["setting"]["requested"] == 2
    assert main([*argv, "--threads", "default", "--out", str(tmp_path / "d")]) == 0
    assert json.loads((tmp_path / "d" / "env.json").read_text())["threads"]["setting"]["requested"] is None
    capsys.readouterr()
    assert main([*argv, "--threads", "0", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "physgrad: error: --threads expects a positive integer or 'default', got '0'"

import os
import resource
import subprocess
import sys
import time

# Four CPU devices for the data-parallel tests (test_distributed.py); set before JAX
# starts. Every other test runs on device 0 alone, as before.
#
# One thread per test process: `make test` runs one pytest-xdist worker per core, and a
# worker whose XLA and OpenBLAS thread pools each want every core oversubscribes the
# machine (the float64 eigh of the Jacobian methods collapses by 10-50x when the pools
# contend). Set before NumPy, SciPy and JAX load their thread pools; a value the caller
# sets wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
# compare, bench and tune default to one Dask worker per core (harness/workers.py); the tests'
# runs take milliseconds, and a cluster per command would cost seconds each: one after the
# other in the test process unless a test passes --workers (or sets the variable) itself.
os.environ.setdefault("PHYSGRAD_WORKERS", "1")
_flags = os.environ.get("XLA_FLAGS", "")
_flags += " --xla_force_host_platform_device_count=4"
if "multi_thread_eigen" not in _flags:
    _flags += " --xla_cpu_multi_thread_eigen=false"  # XLA's one CPU thread flag
# Compilation is most of the suite's time (small programs, each run a few times): LLVM's
# optimisation passes off cut it by about a quarter. XLA's numerics stay IEEE either way (no
# fast-math); the benchmarks and reproductions run with XLA's defaults.
if "xla_backend_optimization_level" not in _flags:
    _flags += " --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
# XLA's CPU fusions through its elemental IR emitters instead of the MLIR fusion emitters:
# compiling a test's program then takes about 40% less CPU (measured cold on test_rollout and
# test_side_effects' update rules, one process, 18-20 → 10-14 CPU-s). The arithmetic is the same
# IEEE operations either way; a float32 result can differ in its last bits (another order of a
# fused sum), as between XLA versions. XLA aborts the process on a flag it does not know, so the
# controlling process asks a fresh interpreter first (one JAX start, about a second) and the
# pytest-xdist workers inherit its verdict in XLA_FLAGS. Only for the fast tier (`-m "not
# slow"`, make test and make test-typed): the slow tier's one-pass/two-pass stabilised-BPTT
# gradient on quantum_control differs by 1e-3 relative in 5 of 10,800 float32 elements with
# these emitters, past its 1e-4 tolerance, and the slow tier keeps XLA's default numerics.
_LEGACY_EMITTERS = "--xla_cpu_use_fusion_emitters=false"
_FAST_TIER = any(a.replace(" ", "") == "notslow" for a in sys.argv)
if "xla_cpu_use_fusion_emitters" not in _flags and "PYTEST_XDIST_WORKER" not in os.environ and _FAST_TIER:
    _probe = subprocess.run(
        [sys.executable, "-c", "import jax; jax.devices('cpu')"],
        env={**os.environ, "XLA_FLAGS": f"{_flags} {_LEGACY_EMITTERS}", "JAX_PLATFORMS": "cpu"},
        capture_output=True,
        timeout=300,
    )
    if _probe.returncode == 0:
        _flags += " " + _LEGACY_EMITTERS
os.environ["XLA_FLAGS"] = _flags.strip()

import jax  # noqa: E402
import pytest  # noqa: E402

# The test session enables float64 itself (importing physgrad does not): the reference
# tests compare against NumPy float64 to 1e-7 and build float64 problems, as equinox's and
# diffrax's own test suites do. tests/test_side_effects.py checks, in fresh interpreters,
# that physgrad works with x64 off and leaves the setting alone.
jax.config.update("jax_enable_x64", True)

# XLA's persistent compilation cache, kept between test runs: a second `make test` on the
# same machine loads most programs from disk instead of compiling them (measured on
# test_methods + test_lm: 173 s of CPU cold, 59 s warm). The key is the program's HLO, the
# compile options and the jax/jaxlib versions, so an entry never serves a changed program.
# PHYSGRAD_TEST_XLA_CACHE names another directory; an empty value turns it off (a cold run,
# as on a fresh machine).
#
# Not JAX's own size cap (`jax_compilation_cache_max_size`): with it every write takes a file
# lock and stats every entry in the directory to find the oldest, so a cold suite's ~5,000
# writes cost quadratic time (the suite measured 27.6 min cold with it). The whole suite's
# cache is ~70 MB; `_trim_cache` deletes the oldest entries beyond a cap once per session.
_XLA_CACHE_CAP = 2 * 2**30
_xla_cache = os.environ.get(
    "PHYSGRAD_TEST_XLA_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "physgrad", "test-xla")
)


def _trim_cache(path: str, cap: int) -> None:
    """Delete the least recently written entries of ``path`` until it holds at most ``cap``
    bytes (entries are written once and never change, so mtime orders them by age)."""
    try:
        entries = [e for e in os.scandir(path) if e.is_file()]
    except FileNotFoundError:
        return
    stats = sorted(((e.stat().st_mtime, e.stat().st_size, e.path) for e in entries), reverse=True)
    total = 0
    for _, size, file in stats:
        total += size
        if total > cap:
            try:
                os.remove(file)
            except FileNotFoundError:  # another worker trimmed it first
                pass


if _xla_cache:
    if "PYTEST_XDIST_WORKER" not in os.environ:  # once, in the controlling process
        _trim_cache(_xla_cache, _XLA_CACHE_CAP)
    jax.config.update("jax_compilation_cache_dir", _xla_cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


# --- jaxtyping's annotations checked at run time (`pytest --jaxtyping`) ---------------------
# Shapes and dtypes of every physgrad function's arguments and results, and Equinox modules'
# fields, checked by beartype through jaxtyping's import hook, installed before the test
# modules import physgrad. The PEP 484 numeric tower: an int is a float, as the annotations
# mean it (`truncation: float` takes 1). A test that passes a wrong type on purpose, to test
# physgrad's own one-line error, says so with `@pytest.mark.unchecked("why")`.
JAXTYPING_CHECKER = "beartype.beartype(conf=beartype.BeartypeConf(is_pep484_tower=True))"


def pytest_addoption(parser):
    parser.addoption(
        "--jaxtyping",
        action="store_true",
        help="check physgrad's jaxtyping annotations at run time (beartype through jaxtyping's import hook)",
    )


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "unchecked(reason): passes a wrong type on purpose; --jaxtyping leaves its calls unchecked"
    )
    if config.getoption("--jaxtyping"):
        if any(name == "physgrad" or name.startswith("physgrad.") for name in sys.modules):
            raise pytest.UsageError("--jaxtyping: physgrad was imported before the import hook could be installed")
        from jaxtyping import install_import_hook

        install_import_hook("physgrad", JAXTYPING_CHECKER)


@pytest.fixture(autouse=True)
def _unchecked(request):
    """A test marked ``unchecked`` runs with jaxtyping's checks off (they are read per call)."""
    if request.node.get_closest_marker("unchecked") is None:
        yield
        return
    import jaxtyping

    before = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", before)


# --- the fast tier's CPU rule -----------------------------------------------------------------
# `make test` stays under 7 minutes on 2 cores only while each fast-tier test is cheap. A test
# whose setup, call and teardown need more than COSTLY_CPU_S seconds of CPU (the subprocesses it
# waits for included) either says why it belongs in the fast tier, with
# `@pytest.mark.costly("why")`, or moves to the slow tier (`@pytest.mark.slow`). The end of a
# run lists the tests that do neither. It is a report, never a failure: CPU time, not wall time,
# so a loaded machine lists the same tests and no test fails for being slow. A test's CPU
# includes what it is the first to compile or build (a module fixture, a program that later
# tests of its worker reuse), so the list can differ a little between `-n auto` and one process.
COSTLY_CPU_S = 5.0
_CPU_START = pytest.StashKey[float]()
_unexplained: list[tuple[float, str]] = []  # (CPU seconds, test id), filled where reports arrive
# PHYSGRAD_TEST_CPU_TABLE=file: every test's CPU seconds, slowest first, written there at the end
# of the run (tab-separated: seconds, worker, test id), to rank a cold suite's costs.
_CPU_TABLE = os.environ.get("PHYSGRAD_TEST_CPU_TABLE", "")
_all_cpu: list[tuple[float, str, str]] = []  # (CPU seconds, worker, test id), every test


def _cpu_seconds() -> float:
    """CPU seconds of this process (every thread) and of its finished subprocesses."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    item.stash[_CPU_START] = _cpu_seconds()
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    if call.when == "teardown":  # the whole test is done; xdist ships user_properties to the controller
        explained = item.get_closest_marker("slow") is not None or item.get_closest_marker("costly") is not None
        item.user_properties.append(("cpu_s", round(_cpu_seconds() - item.stash[_CPU_START], 2)))
        item.user_properties.append(("cpu_explained", explained))
    yield


def pytest_runtest_logreport(report):
    if report.when == "teardown":
        props = dict(report.user_properties)
        if props.get("cpu_s", 0.0) > COSTLY_CPU_S and not props.get("cpu_explained", True):
            _unexplained.append((props["cpu_s"], report.nodeid))
        if _CPU_TABLE and "cpu_s" in props:
            node = getattr(report, "node", None)  # pytest-xdist's worker, on the controller
            _all_cpu.append((props["cpu_s"], node.gateway.id if node is not None else "-", report.nodeid))


def pytest_terminal_summary(terminalreporter):
    if _CPU_TABLE and _all_cpu:
        with open(_CPU_TABLE, "w") as f:
            for cpu, worker, nodeid in sorted(_all_cpu, reverse=True):
                f.write(f"{cpu:.2f}\t{worker}\t{nodeid}\n")
    if _unexplained:
        terminalreporter.write_sep("=", f"tests over {COSTLY_CPU_S:g} s of CPU that say no reason")
        for cpu, nodeid in sorted(_unexplained, reverse=True):
            terminalreporter.write_line(f"{cpu:7.1f}s  {nodeid}")
        terminalreporter.write_line(
            'Mark each @pytest.mark.costly("why it is in the fast tier") or @pytest.mark.slow (CONTRIBUTING.md).'
        )

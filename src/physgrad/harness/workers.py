"""Independent runs in parallel: in this process, or on the workers of a Dask cluster.

A calibrated budget is a number of steps (:mod:`physgrad.harness.calibration`), so a run's
numbers do not depend on when or where it runs: runs may go to other processes or machines
without changing a digit. An executor takes **jobs** (picklable callables, each one run
into its own run directory: :class:`ConfiguredRun`, :class:`ObjectRun`) and yields their
results as they finish:

- :class:`InProcess` runs them one after the other here (``--workers 1``);
- :class:`Dask` submits them to Dask distributed (Rocklin 2015, "Dask: Parallel Computation
  with Blocked algorithms and Task Scheduling"; ``distributed.Client``): by default a
  ``LocalCluster`` started in this process with ``workers`` worker processes of one thread
  each (nothing to install or start), or the scheduler at ``scheduler`` (``tcp://HOST:8786``,
  a cluster the user runs), or any Dask ``client``/cluster object (``dask_jobqueue.SLURMCluster``).

Each run keeps its own run directory, lock, checkpoints and resume (:func:`physgrad.fit`).
A worker that dies takes its run's work since the last checkpoint with it: the scheduler
hands the job to another worker (``distributed.scheduler.allowed-failures``, and
``retries`` for a job that raised), which resumes the run from its checkpoint. A worker
keeps the programs it compiled (:mod:`physgrad.engine.programs`), so each worker compiles a
(problem, method, shapes) step once, as the single process does. Every worker process
runs with ``threads`` threads per pool (:func:`physgrad.cpu.process_threads`), set before
its JAX backend starts. The cluster started here runs Dask's periodic bookkeeping less often
(:data:`CLUSTER_CONFIG`), so that it takes less of the cores the runs use; in any cluster a
run's CPU seconds leave out its worker's event loop (:mod:`physgrad.engine.cpu_clock`).
"""

from __future__ import annotations

import abc
import dataclasses
import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from ..engine import AbstractSplit, Budget, TrainSettings
from ..engine.splits import TEST_SPLIT
from ..errors import ConfigError

Job = Callable[[], Any]


WORKERS_VARIABLE = "PHYSGRAD_WORKERS"
# JAX's accelerator plugins: where one is installed (and JAX_PLATFORMS does not say cpu), the
# runs would share the accelerator, and every worker process would claim most of its memory
# (JAX preallocates 75% per process), so the default is one worker.
ACCELERATOR_PLUGINS = ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_rocm60_plugin", "jax_rocm7_plugin", "libtpu")


# Dask's configuration in the processes of the LocalCluster that Dask() starts (never in a
# cluster the user gives, nor left set in the caller's process). Dask's periodic bookkeeping
# costs CPU in proportion to wall-clock time, on the cores the runs use: an idle worker took
# 30 ms of CPU per second with the statistical profiler, 19-24 ms without it, and 4 ms with the
# slower ticks and monitors below; the process that starts the cluster (scheduler and nannies)
# 33-53 ms against 9 (2 workers, 2 cores under load 10-17, docs/benchmark.md).
CLUSTER_CONFIG: dict[str, Any] = {
    # no sampling of each worker thread's stack every 10 ms
    "distributed.worker.profile.enabled": False,
    # the event loop's responsiveness check, 20 ms by default: 50 wake-ups per second in every
    # process; a loop blocked for 3 s (admin.tick.limit) is still reported
    "distributed.admin.tick.interval": "1s",
    # CPU, memory, network and disk samples for the dashboard and the heartbeat's metrics
    # (500 ms by default); pausing, spilling and the nanny's restart read memory themselves
    "distributed.admin.system-monitor.interval": "5s",
    # the worker's pause/spill check and the nanny's restart of a worker over its memory
    # limit (100 ms by default): a runaway run is still stopped within half a second
    "distributed.worker.memory.monitor-interval": "500ms",
}


def default_workers() -> int:
    """The ``--workers`` default: ``$PHYSGRAD_WORKERS`` where it is set (the test suite sets
    1: its runs are too short to pay for a cluster), else 1 where JAX has an accelerator
    plugin (one device shared by every worker), else the machine's cores available to this
    process (a process pinned with ``taskset -c 0`` gets 1, and no cluster)."""
    given = os.environ.get(WORKERS_VARIABLE, "").strip()
    if given:
        if not given.isdigit() or int(given) < 1:
            raise ConfigError(f"${WORKERS_VARIABLE} must be a number of workers of at least 1, got {given!r}")
        return int(given)
    if os.environ.get("JAX_PLATFORMS", "").strip().lower() != "cpu" and _accelerator_plugin():
        return 1
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _accelerator_plugin() -> bool:
    import importlib.util

    return any(importlib.util.find_spec(name) is not None for name in ACCELERATOR_PLUGINS)


class AbstractExecutor(abc.ABC):
    """Runs independent jobs; ``run`` yields ``(index, result, error)`` as each job finishes
    (``error`` None on success, else the exception it raised). ``slots`` is how many jobs
    run at once. Use as a context manager: a cluster it started is closed on exit."""

    @property
    @abc.abstractmethod
    def slots(self) -> int: ...

    @abc.abstractmethod
    def run(self, jobs: Sequence[Job]) -> Iterator[tuple[int, Any, BaseException | None]]: ...

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:  # noqa: B027 (nothing to release by default)
        """Release what the executor started (nothing by default)."""


@dataclasses.dataclass
class InProcess(AbstractExecutor):
    """One job after the other in this process (a KeyboardInterrupt stops at once)."""

    @property
    def slots(self) -> int:
        return 1

    def run(self, jobs):
        for i, job in enumerate(jobs):
            try:
                result = job()
            except Exception as e:  # recorded by the caller; KeyboardInterrupt stops
                yield i, None, e
                continue
            yield i, result, None


class Dask(AbstractExecutor):
    """Jobs on Dask distributed workers (see the module docstring).

    Arguments (at most one of ``scheduler`` and ``client``):
        workers: worker processes of the in-process ``LocalCluster`` (default: the machine's
            cores), one thread each.
        scheduler: the address of a running scheduler (``tcp://HOST:8786``).
        client: a ``distributed.Client``, or a cluster object (``LocalCluster``,
            ``dask_jobqueue.SLURMCluster``, ...) that a client is made for.
        retries: times a job that raised is tried again (a dead worker's job is handed on
            by the scheduler regardless, up to ``distributed.scheduler.allowed-failures``).
        threads: threads per pool in each worker process (default 1).
    """

    def __init__(self, workers: int | None = None, *, scheduler: str | None = None, client: Any = None,
                 retries: int = 2, threads: int | None = 1):  # fmt: skip
        if scheduler and client is not None:
            raise ConfigError("give a scheduler address or a client, not both")
        if workers is not None and workers < 1:
            raise ConfigError(f"workers must be at least 1, got {workers}")
        self.workers, self.scheduler, self.retries, self.threads = workers, scheduler, retries, threads
        self._given, self._client, self._cluster = client, None, None

    @property
    def client(self):
        """The ``distributed.Client`` (the in-process cluster is started on first use)."""
        if self._client is None:
            from distributed import Client, LocalCluster

            given = self._given
            if given is not None:
                self._client = given if isinstance(given, Client) else Client(given)
            elif self.scheduler:
                self._client = Client(self.scheduler)
            else:
                import dask.config

                # Worker processes (JAX is not fork-safe; each has its own compiled programs),
                # one thread each; no dashboard (a port nobody asked for); Dask's own periodic
                # work slowed down (CLUSTER_CONFIG). Each nanny copies the configuration to its
                # worker as it is made; the caller's is restored on leaving the block.
                with dask.config.set(CLUSTER_CONFIG):
                    self._cluster = LocalCluster(n_workers=self.workers or default_workers(), threads_per_worker=1,
                                                 processes=True, dashboard_address=None)  # type: ignore[arg-type]  # fmt: skip
                self._client = Client(self._cluster)
        return self._client

    @property
    def slots(self) -> int:
        if self._given is None and not self.scheduler:
            return self.workers or default_workers()
        return max(1, sum(self.client.nthreads().values()))  # type: ignore[union-attr]

    def run(self, jobs):
        from distributed import as_completed

        if not jobs:  # nothing to do (a resumed study whose runs are finished): no cluster started
            return
        futures = {self.client.submit(_call, job, self.threads, pure=False, retries=self.retries): i
                   for i, job in enumerate(jobs)}  # fmt: skip
        for future in as_completed(list(futures)):
            i = futures[future]
            try:
                yield i, future.result(), None
            except Exception as e:  # the job's own error, re-raised here by Dask
                yield i, None, e

    def close(self) -> None:
        if self._given is None and self._client is not None:  # only what this executor started
            self._client.close()
            if self._cluster is not None:
                self._cluster.close()
        self._client = self._cluster = None


def _call(job: Job, threads: int | None) -> Any:
    """A job on a worker, under the worker's thread setting (set before JAX's backend
    starts, at the worker's first job)."""
    from ..cpu import process_threads

    with process_threads(threads):
        return job()


def executor_for(workers: int | None = 1, scheduler: str | None = None, client: Any = None) -> AbstractExecutor:
    """The executor of the command line's ``--workers N`` / ``--scheduler ADDRESS`` (and of
    the library's ``workers=``/``client=``): in this process for one worker and no cluster,
    else :class:`Dask`."""
    if client is not None or scheduler:
        return Dask(scheduler=scheduler, client=client)
    if workers is None:
        workers = default_workers()
    return InProcess() if workers <= 1 else Dask(workers)


# --- jobs: one run each, into its own run directory -------------------------------------------
@dataclasses.dataclass(frozen=True)
class ConfiguredRun:
    """A run of the command line's configuration (:class:`~physgrad.harness.config.RunConfig`)
    into ``run_dir``, resumed where it stopped, on ``split`` (a tuning trial's
    :class:`~physgrad.HoldOut`: validation data in place of the test split). Returns the
    run's summary."""

    config: Any  # RunConfig
    run_dir: str
    split: AbstractSplit = TEST_SPLIT
    devices: int | str | None = 1

    def __call__(self) -> dict[str, Any]:
        from .train import train

        return train(self.config, self.run_dir, resume=True, devices=self.devices, split=self.split)


@dataclasses.dataclass(frozen=True)
class ObjectRun:
    """A run of a user's own problem object with a registered method (``hyperparameters``
    complete), into ``run_dir``, resumed where it stopped, on ``split`` as in
    :class:`ConfiguredRun`."""

    problem: Any  # AbstractProblem
    method: str
    hyperparameters: dict[str, Any]
    batch_size: int
    seed: int
    budget: Budget
    run_dir: str
    settings: TrainSettings = TrainSettings()
    split: AbstractSplit = TEST_SPLIT

    def __call__(self) -> dict[str, Any]:
        from ..engine import Phase, fit
        from .registry import METHODS

        phase = Phase(METHODS[self.method](**self.hyperparameters), None, self.batch_size, self.method)
        record = {"problem": self.problem.name, "method": self.method, "seed": self.seed,
                  "budget": self.budget.to_dict(), "hyperparameters": self.hyperparameters,
                  "batch_size": self.batch_size,
                  "validation": self.split.note}  # fmt: skip
        return fit(self.problem, [phase], budget=self.budget, out=self.run_dir, seed=self.seed,
                   settings=self.settings, split=self.split, resume=True, record=record,
                   name=self.method).summary  # fmt: skip


def run_pending(executor: Any, pending, log, *, record_failures: bool, echo, devices: int | str | None = 1) -> None:
    """A study's runs left to do (``(prefix, config, run_dir)``, from
    :func:`physgrad.harness.study.compare`) on ``executor``, all at once; each finished run
    is echoed as it comes back, a failed one recorded in ``log`` (``record_failures``) or
    raised, as the one-after-the-other loop does."""
    from .console import describe_run
    from .failures import recordable

    jobs = [ConfiguredRun(config, run_directory(run_dir), devices=devices) for _, config, run_dir in pending]
    for i, summary, error in executor.run(jobs):
        prefix, config, run_dir = pending[i]
        name = Path(run_dir).name
        if error is not None:
            if not (record_failures and isinstance(error, Exception) and recordable(error)):
                raise error
            echo(f"{prefix}: failed, recorded ({log.record(name, config.method, config.seed, error)})")
            continue
        log.clear(name)
        echo(f"{prefix}: {describe_run(summary)}")


def run_directory(path: str | Path) -> str:
    """A run directory as the text a job carries (absolute: a worker's working directory may differ)."""
    return str(Path(path).resolve())


__all__ = [
    "AbstractExecutor",
    "CLUSTER_CONFIG",
    "ConfiguredRun",
    "Dask",
    "InProcess",
    "ObjectRun",
    "default_workers",
    "executor_for",
    "run_pending",
]

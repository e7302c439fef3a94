"""Runs on Dask workers (harness/workers.py): the same tables with one process and with two
worker processes, one of which is killed mid-run; the executors' contract."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from physgrad import Budget
from physgrad.harness.study import compare, read_csv
from physgrad.harness.workers import Dask, InProcess, default_workers, executor_for

# Numbers a run writes that must not depend on where it ran (times and directories may).
SAME = ("problem", "method", "seed", "status", "steps", "epochs", "final_train_loss", "final_test_loss",
        "best_test_loss", "diverged_step", "last_finite_loss")  # fmt: skip


def _table(out):
    rows = read_csv(out / "summary.csv")
    return sorted(tuple(r[k] for k in SAME) for r in rows)


def _curves(out):
    rows = read_csv(out / "results.csv")
    return sorted((r["method"], r["seed"], r["step"], r["split"], r["metric"], r["value"]) for r in rows
                  if not r["metric"].startswith("step_") and r["metric"] != "time_per_step")  # fmt: skip


def test_executor_for_picks_in_process_for_one_worker():
    assert isinstance(executor_for(1), InProcess)
    assert isinstance(executor_for(2), Dask) and executor_for(2).slots == 2
    assert default_workers() >= 1
    results = sorted(InProcess().run([lambda: 1, lambda: 1 / 0]), key=lambda r: r[0])
    assert results[0] == (0, 1, None) and isinstance(results[1][2], ZeroDivisionError)


def test_the_default_workers_are_the_cores_unless_the_variable_or_an_accelerator_says_otherwise(monkeypatch):
    import os

    from physgrad.errors import ConfigError
    from physgrad.harness import workers

    monkeypatch.setenv("PHYSGRAD_WORKERS", "3")
    assert default_workers() == 3  # the variable wins (tests/conftest.py sets 1)
    monkeypatch.delenv("PHYSGRAD_WORKERS")
    monkeypatch.setattr(workers, "_accelerator_plugin", lambda: False)
    assert default_workers() == len(os.sched_getaffinity(0))
    monkeypatch.setattr(workers, "_accelerator_plugin", lambda: True)
    monkeypatch.setenv("JAX_PLATFORMS", "cuda")
    assert default_workers() == 1  # one accelerator shared by every worker process: one worker
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert default_workers() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("PHYSGRAD_WORKERS", "zero")
    with pytest.raises(ConfigError, match="PHYSGRAD_WORKERS must be a number of workers"):
        default_workers()


@pytest.mark.slow  # a LocalCluster of two worker processes and a study run twice: ~1-2 minutes on 2 cores
def test_two_workers_one_killed_mid_run_give_the_sequential_tables(tmp_path):
    """A study on a LocalCluster of two worker processes, one killed (SIGKILL) while it
    trains: the scheduler hands its run to a worker, which resumes it from its checkpoint
    (taken at each evaluation), and the study's tables equal those of the same study run
    one run after the other."""
    settings = {"eval_every": "100", "batch_size": "64", "checkpoint_seconds": "600"}  # checkpoints at the evaluations
    args = ("hig_toy", ["adam", "hig"], range(2), Budget(steps=1500))
    # The sequential reference on one worker process: worker processes start JAX with the
    # thread setting of physgrad's processes, which this test process (conftest.py) does not.
    with Dask(1) as one:
        compare(*args, tmp_path / "sequential", settings=settings, echo=lambda line: None, executor=one)
    killed = []
    with Dask(2) as executor:
        client = executor.client
        client.wait_for_workers(2)
        pids = client.run(os.getpid)

        def kill_a_busy_worker():
            deadline = time.monotonic() + 240
            while time.monotonic() < deadline and not killed:
                busy = [w for w, keys in client.processing().items() if keys]
                started = list((tmp_path / "parallel" / "runs").glob("*/checkpoint"))
                if busy and started:
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(busy[0])
                time.sleep(0.05)

        killer = threading.Thread(target=kill_a_busy_worker, daemon=True)
        killer.start()
        compare(*args, tmp_path / "parallel", settings=settings, echo=lambda line: None, executor=executor)
        killer.join()
    assert killed, "no worker was killed mid-run: the runs were too short to catch one"
    assert _table(tmp_path / "parallel") == _table(tmp_path / "sequential")
    assert _curves(tmp_path / "parallel") == _curves(tmp_path / "sequential")


@pytest.mark.slow  # starts a LocalCluster of one worker process: a few seconds, more on a loaded machine
def test_the_local_clusters_processes_get_the_cluster_config_and_the_caller_keeps_its_own():
    """The cluster the executor starts runs with CLUSTER_CONFIG (no statistical profiler,
    slower ticks and monitors): its worker process reads every value, and its scheduler and
    nanny, which live in this process, were built with them; this process's configuration
    is left as it was, and a cluster the caller gives is not touched."""
    import dask
    import distributed  # noqa: F401  (its configuration's defaults)
    from dask.utils import parse_timedelta

    from physgrad.harness.workers import CLUSTER_CONFIG

    before = {key: dask.config.get(key) for key in CLUSTER_CONFIG}
    assert before != CLUSTER_CONFIG  # Dask's defaults differ, so the check below means something
    executor = Dask(workers=1)
    try:
        seen = executor.client.run(
            lambda keys: {k: __import__("dask").config.get(k) for k in keys}, list(CLUSTER_CONFIG)
        )
        assert list(seen.values()) == [CLUSTER_CONFIG]
        cluster = executor._cluster
        assert cluster is not None
        tick = parse_timedelta(CLUSTER_CONFIG["distributed.admin.tick.interval"])
        assert cluster.scheduler._tick_interval == tick  # type: ignore[union-attr]
        (nanny,) = cluster.workers.values()
        assert nanny._tick_interval == tick
        assert nanny.memory_manager.memory_monitor_interval == parse_timedelta(
            CLUSTER_CONFIG["distributed.worker.memory.monitor-interval"])  # fmt: skip
        assert {key: dask.config.get(key) for key in CLUSTER_CONFIG} == before  # restored while the cluster runs
        given = Dask(client=executor.client)  # a cluster the caller gives: used as it is
        assert given.client is executor.client and given._cluster is None
    finally:
        executor.close()
    assert {key: dask.config.get(key) for key in CLUSTER_CONFIG} == before

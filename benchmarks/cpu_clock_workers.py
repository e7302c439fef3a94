"""What a Dask worker's own CPU adds to a run's CPU step, and the calibrated against the in-run step.

A run's ``cpu_time_per_step`` and the ``cpu`` calibration clock are
:func:`physgrad.engine.cpu_clock.run_cpu_time`: the process's CPU seconds less those of its
other Python threads. ``time.process_time`` also counted the worker's event loop, whose CPU
grows with wall-clock time, so load inflated a run's CPU step (issue 50, item 4). Two parts:

``idle``: the CPU per wall-clock second of each worker process of an idle ``LocalCluster``
as :class:`physgrad.harness.workers.Dask` starts it (JAX imported, no task) and of this
process (the scheduler and the nannies live here), per thread, read from ``/proc`` over
``--seconds``; with physgrad's ``CLUSTER_CONFIG`` and with Dask's defaults but no profiler.

``study``: ``compare hig_toy`` of Adam, GN and HIG (5 calibrated seconds on the ``cpu``
clock, seed 0) on ``--workers`` (1: in this process). Each run reads both clocks at the
same chunk boundaries, so the last columns compare them over the same chunks; the ratio is
the in-run over the calibrated CPU ms/step (issue 50's check: within 1.2x on an idle
machine). ``--dask-defaults`` starts the cluster without ``CLUSTER_CONFIG`` (profiler off).

    python benchmarks/cpu_clock_workers.py idle [--seconds 30]
    python benchmarks/cpu_clock_workers.py study [--workers 2] [--out DIR] [--dask-defaults]

Linux only (``/proc`` and per-thread CPU clocks). Print the load beside every number.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

NO_PROFILER = {"distributed.worker.profile.enabled": False}


def _ticks(path: str) -> int:
    """utime + stime (clock ticks) of a /proc stat file."""
    text = Path(path).read_text()
    fields = text[text.rindex(")") + 2 :].split()
    return int(fields[11]) + int(fields[12])


def _threads(pid: int) -> dict[str, int]:
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out[tid] = _ticks(f"/proc/{pid}/task/{tid}/stat")
        except FileNotFoundError:  # ended meanwhile
            pass
    return out


def _thread_names() -> dict[str, str]:
    return {str(t.native_id): t.name for t in threading.enumerate()}


def idle(seconds: float, config: dict | None) -> None:
    from physgrad.harness import workers

    if config is not None:
        workers.CLUSTER_CONFIG = config  # read when the cluster starts
    hz = os.sysconf("SC_CLK_TCK")
    with workers.Dask(2) as executor:
        client = executor.client
        client.wait_for_workers(2)
        client.run(lambda: float(__import__("jax").numpy.ones(3).sum()))  # JAX's backend and threads, as a run has
        pids = {f"worker {i}": p for i, p in enumerate(client.run(os.getpid).values())} | {"this process": os.getpid()}
        names = {str(pids[f"worker {i}"]): n for i, n in enumerate(client.run(_thread_names).values())}
        names[str(os.getpid())] = _thread_names()
        time.sleep(3)
        before = {k: (_ticks(f"/proc/{p}/stat"), _threads(p)) for k, p in pids.items()}
        t0 = time.perf_counter()
        time.sleep(seconds)
        wall = time.perf_counter() - t0
        after = {k: (_ticks(f"/proc/{p}/stat"), _threads(p)) for k, p in pids.items()}
    label = "Dask's defaults, no profiler" if config is not None else "physgrad's CLUSTER_CONFIG"
    print(f"{label}: idle CPU over {wall:.0f} s, load {os.getloadavg()}")
    for key, pid in pids.items():
        per_thread: dict[str, float] = {}
        for tid, ticks in after[key][1].items():
            name = names.get(str(pid), {}).get(tid, "native")
            used = (ticks - before[key][1].get(tid, 0)) * 1e3 / hz / wall
            per_thread[name] = round(per_thread.get(name, 0.0) + used, 1)
        total = (after[key][0] - before[key][0]) * 1e3 / hz / wall
        print(f"  {key}: {total:.1f} ms of CPU per s; by thread {per_thread}")


class BothClocks:
    """A job that runs its run with the engine's CPU clock wrapped to read time.process_time
    at the same instants, and writes both totals over the chunks to the run's both_clocks.json."""

    def __init__(self, job):
        self.job = job

    def __call__(self):
        import physgrad.engine.run as run
        from physgrad.engine.cpu_clock import run_cpu_time

        reads = []

        def clock():
            reads.append((time.process_time(), run_cpu_time()))
            return reads[-1][1]

        run.run_cpu_time = clock  # type: ignore[attr-defined]
        summary = self.job()
        pairs = list(zip(reads[0::2], reads[1::2]))  # (before the dispatch, after the read-back) of each chunk
        totals = {name: sum(end[i] - start[i] for start, end in pairs) for i, name in enumerate(("process", "run"))}
        Path(self.job.run_dir, "both_clocks.json").write_text(json.dumps({**totals, "steps": summary["cpu_steps"]}))
        return summary


def study(workers: int, out: Path, config: dict | None) -> None:
    os.environ["PHYSGRAD_CALIBRATION_CLOCK"] = "cpu"
    from physgrad import Budget
    from physgrad.harness import workers as w
    from physgrad.harness.study import compare

    if config is not None:
        w.CLUSTER_CONFIG = config
    executor = w.Dask(workers) if workers > 1 else w.InProcess()
    plain_run = executor.run
    executor.run = lambda jobs: plain_run([BothClocks(j) for j in jobs])  # type: ignore[method-assign]
    load = os.getloadavg()
    with executor:
        compare("hig_toy", ["adam", "gn", "hig"], range(1), Budget(seconds=5), out, echo=print, executor=executor)
    print(f"{workers} worker(s), {'Dask defaults, no profiler' if config else 'CLUSTER_CONFIG'}; "
          f"load {load} before, {os.getloadavg()} after")  # fmt: skip
    calibration = json.loads((out / "calibration.json").read_text())
    print("method  calibrated  in-run (run clock)  ratio  in-run (process_time)  ratio  wall ms/step")
    for run_dir in sorted((out / "runs").iterdir()):
        method = run_dir.name.split("-")[0]
        both = json.loads((run_dir / "both_clocks.json").read_text())
        wall = json.loads((run_dir / "summary.json").read_text())["time_per_step"] * 1e3
        cal = calibration["methods"][method]["stages"][0]["seconds"] * 1e3
        mine, process = (both[k] / both["steps"] * 1e3 for k in ("run", "process"))
        print(
            f"{method:6}  {cal:10.3f}  {mine:18.3f}  {mine / cal:5.2f}  {process:21.3f}  {process / cal:5.2f}  {wall:12.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("part", choices=["idle", "study"])
    parser.add_argument("--seconds", type=float, default=30.0, help="idle: wall-clock seconds to watch")
    parser.add_argument("--workers", type=int, default=2, help="study: worker processes (1: this process)")
    parser.add_argument("--out", type=Path, default=None, help="study: directory (default a fresh temporary one)")
    parser.add_argument("--dask-defaults", action="store_true", help="Dask's configuration, profiler off")
    args = parser.parse_args()
    if not sys.platform.startswith("linux"):
        raise SystemExit("Linux only: /proc and per-thread CPU clocks")
    import distributed  # noqa: F401  (Dask's configuration defaults, before anything sets a key)

    config = NO_PROFILER if args.dask_defaults else None
    if args.part == "idle":
        idle(args.seconds, None)
        idle(args.seconds, NO_PROFILER)
    else:
        study(args.workers, args.out or Path(tempfile.mkdtemp(prefix="cpu-clock-")), config)


if __name__ == "__main__":
    main()

"""What a run records: evaluations in ``metrics.csv`` and in memory, for the history
(:class:`Recorder`), checkpoints of the loop state (:class:`Checkpointer`), the final files
and summary (:func:`finish`), and reading run directories back (:func:`read_summary`,
:func:`is_complete`; ``metrics.csv``, plain or packed: :mod:`physgrad.engine.packed`).
Every file is written whole (:mod:`physgrad.engine.rundir`); a run in memory
(``fit(..., out=None)``) writes none of them.

A run directory holds ``config.json`` (what the caller says identifies the run),
``metrics.csv`` (long format: step, wall_time, split, metric, value), ``env.json``,
``summary.json``, ``test_cases.json``, ``params.eqx`` (the final network) and
``checkpoint/`` for ``resume``.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import math
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from .. import cpu, distributed
from ..errors import ConfigError
from ..nets import parameter_count
from ..precision import x64_enabled
from . import rundir
from .callbacks import Callbacks
from .packed import gzip_bytes, kept_path, open_kept, pack_file, packed_path, read_metrics  # noqa: F401 — their old home
from .result import Row, rows_from_metrics
from .step import make_evaluate
from .strategies import Fidelity, Placement
from .types import SESSION_COUNTERS, Budget, Ending, Setup, TrainSettings, TrainState

METRICS_HEADER = ("step", "wall_time", "split", "metric", "value")
FINAL_STATUSES = ("finished", "diverged")


class MetricsLog:
    """Appends long-format rows to ``metrics.csv``. On resume it keeps the rows up to the
    checkpoint's step (``kept``; a row torn by a kill during an append is dropped) and
    rewrites the file atomically, so a kill never leaves half a table."""

    def __init__(self, path: Path | None, *, keep_until_step: int | None = None, enabled: bool = True):
        self.path = path
        self.enabled = enabled and path is not None
        self.kept: list[dict[str, str]] = []
        if path is None or not self.enabled:
            return
        if keep_until_step is not None and path.exists():
            self.kept = [r for r in _complete_rows(path) if int(r["step"]) <= keep_until_step]
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(METRICS_HEADER)
        writer.writerows([[r[k] for k in METRICS_HEADER] for r in self.kept])
        rundir.atomic_write(path, text.getvalue())

    def write(self, step: int, wall_time: float, values: dict[tuple[str, str], float]):
        if self.path is None or not self.enabled:
            return
        with self.path.open("a", newline="") as f:
            writer = csv.writer(f)
            for (split, metric), value in values.items():
                writer.writerow([step, f"{wall_time:.6f}", split, metric, repr(float(value))])


def _numbers(step: str, value: str) -> bool:
    """Whether a row's step and value parse (those of a torn row may not)."""
    try:
        int(step)
        float(value)
    except ValueError:
        return False
    return True


def _complete_rows(path: Path) -> list[dict[str, str]]:
    """The rows of ``metrics.csv`` that were written whole (a kill during an append can cut
    the last line anywhere, even into a shorter number)."""
    with path.open(newline="") as f:
        text = f.read()
    rows = []
    for r in csv.DictReader(io.StringIO(text[: text.rfind("\n") + 1])):
        if all(r.get(k) for k in METRICS_HEADER) and None not in r and _numbers(r["step"], r["value"]):
            rows.append(r)
    return rows


class Recorder:
    """Evaluation at the scheduled steps: full train/test (and val) metrics, the methods'
    step statistics averaged since the last evaluation (``step_<name>``), written to
    ``metrics.csv`` and kept as :attr:`rows` (the run's history); tells the callbacks
    (``on_eval``); feeds PRDP the validation error."""

    def __init__(
        self,
        setup: Setup,
        *,
        settings: TrainSettings,
        placement: Placement,
        fidelity: Fidelity,
        log: MetricsLog,
        callbacks: Callbacks | None = None,
    ):
        self.settings, self.placement, self.fidelity, self.log = settings, placement, fidelity, log
        self.callbacks = callbacks or Callbacks()
        self.last: dict[str, float] = {}
        self.rows: list[Row] = []  # every evaluation: (step, training seconds, {split_metric: value})
        train = setup.data["train"]
        n_train = jax.tree.leaves(train)[0].shape[0]
        # The train-split evaluation may be limited to its first eval_samples samples (large
        # image datasets would otherwise cost more per evaluation than many training steps).
        # A problem's own default takes a strided subset: its windows are stored trajectory
        # by trajectory, so the first N would all come from one trajectory.
        n_eval = settings.eval_samples or setup.problem.default_eval_samples or None
        stride = max(1, n_train // n_eval) if n_eval and not settings.eval_samples else 1
        self.splits = {"train": placement.put(jax.tree.map(lambda a: a[::stride][:n_eval], train)),
                       "test": placement.put(setup.data["test"])}  # fmt: skip
        # A HoldOut run's test split is the problem's val split, the same object: evaluated once
        self.val_is_test = setup.data.get("val") is not None and setup.data.get("val") is setup.data["test"]
        self.val = None if self.val_is_test else placement.put(setup.data.get("val"))
        self.use(setup)

    def use(self, setup: Setup):
        self.evaluate = make_evaluate(setup)

    def accumulate(self, state: TrainState, stats: dict[str, Any], taken: int) -> TrainState:
        """The step statistics of a chunk's first ``taken`` steps (``stats[name]``: one row
        per step, :func:`~physgrad.engine.step.make_steps`) added to the window since the
        last evaluation and to the run's totals, one step after the other in float64 (so
        the sums do not depend on how the steps were chunked: a resumed run logs the same)."""
        totals, window = dict(state.stat_totals), dict(state.stat_window)
        for name, values in stats.items():
            if name == "loss":
                continue
            for value in np.asarray(values[:taken], np.float64).tolist():
                if not math.isfinite(value):  # e.g. the norm of a skipped NaN gradient
                    continue
                total, count = window.get(name, (0.0, 0))
                window[name] = [total + value, count + 1]
                totals[name] = totals.get(name, 0.0) + value
        return state._replace(stat_totals=totals, stat_window=window)

    def restore(self, rows: list[dict[str, str]]) -> int | None:
        """After a resume: the metrics of the last evaluation logged (as if this recorder had
        made it, for the summary); returns its step (None without one)."""
        if not rows:
            return None
        self.rows = rows_from_metrics(rows)
        step = max(int(r["step"]) for r in rows)
        self.last.update({f"{r['split']}_{r['metric']}": float(r["value"]) for r in rows if int(r["step"]) == step})
        return step

    def __call__(self, state: TrainState, final: bool) -> tuple[TrainState, bool]:
        """Evaluate and log at ``state.step``; returns the state and whether the losses are finite."""
        rundir.fault("evaluating")  # test hook: a signal while an evaluation runs
        window = state.stat_window  # sorted: a resumed window (from JSON) logs in the same order
        values = {("train", f"step_{n}"): window[n][0] / window[n][1] for n in sorted(window)}
        state = state._replace(stat_window={})
        with self.placement.scope():
            for split, data in self.splits.items():
                values.update({(split, k): float(v) for k, v in self.evaluate(state.params, data).items()})
            val = self.evaluate(state.params, self.val) if self.val is not None else {}
        if self.val_is_test:
            val = {metric: v for (split, metric), v in values.items() if split == "test"}
        if state.step > 0:
            values[("train", "time_per_step")] = state.train_time / state.step
        if self.fidelity.name:
            values[("train", "solver_iterations")] = self.fidelity.iterations(state)
        values.update({("val", k): float(v) for k, v in val.items()})
        if self.settings.prdp and not final:
            state = self.fidelity.observe(state, float(val.get("rel_error", val["loss"])))
        self.log.write(state.step, state.train_time, values)
        metrics = {f"{split}_{metric}": float(v) for (split, metric), v in values.items()}
        self.last.update(metrics)
        self.rows.append((state.step, state.train_time, metrics))
        self.callbacks.on_eval(state.step, {"time": state.train_time, **metrics})
        test = self.last["test_loss"]
        if math.isfinite(test):
            state = state._replace(best_test_loss=min(state.best_test_loss, test))
        return state, math.isfinite(self.last["train_loss"]) and math.isfinite(test)


@dataclasses.dataclass
class Checkpointer:
    """Saves the :class:`TrainState` once ``seconds`` of wall-clock time have passed since
    the previous save (or the start), at every evaluation and at the end, so a kill loses at
    most that much work. Each save is one atomic commit of ``checkpoint/`` (arrays in
    ``state.eqx``, host scalars in ``counters.json``, sizes and checksums in
    ``manifest.json``: :func:`physgrad.engine.rundir.save_checkpoint`).

    Loading verifies the manifest; a checkpoint of an older physgrad (no manifest) still
    loads, unverified. Without a run directory (``run_dir`` None: a run in memory) it
    saves nothing. After each save the callbacks' ``on_checkpoint`` is called."""

    run_dir: Path | None
    seconds: float
    writer: bool
    callbacks: Callbacks = dataclasses.field(default_factory=Callbacks)
    last: float = dataclasses.field(default_factory=time.monotonic)

    @property
    def writes(self) -> bool:
        """Whether this process writes the run's files (a run directory, process 0)."""
        return self.writer and self.run_dir is not None

    def seconds_left(self) -> float:
        """Wall-clock seconds until :meth:`maybe` saves (<= 0: due; inf in memory)."""
        return self.seconds - (time.monotonic() - self.last) if self.run_dir is not None else math.inf

    def maybe(self, state: TrainState):
        if self.seconds_left() <= 0:
            self.save(state)

    def save(self, state: TrainState):
        if self.run_dir is None:
            return
        if self.writer:
            buffer = io.BytesIO()
            eqx.tree_serialise_leaves(buffer, distributed.to_host((state.params, state.opt_state)))
            counters = rundir.json_text(state.counters()).encode()
            rundir.save_checkpoint(
                self.run_dir, {"state.eqx": buffer.getvalue(), "counters.json": counters}, state.step
            )
            self.callbacks.on_checkpoint(state.step, rundir.checkpoint_path(self.run_dir) or self.run_dir)
        self.last = time.monotonic()  # the interval counts from the end of a save

    def exists(self) -> bool:
        return self.run_dir is not None and rundir.checkpoint_path(self.run_dir) is not None

    def load(self, like: Callable[[dict[str, Any]], TrainState]) -> TrainState | None:
        """The checkpointed state (None without one); ``like(counters)`` gives its structure
        (the optimizer state depends on the stage it was taken in). Damaged files are a
        one-line ConfigError (:func:`physgrad.engine.rundir.load_checkpoint`); files that verify
        but do not fit ``like`` were written by another version of the method."""
        found = rundir.load_checkpoint(self.run_dir) if self.run_dir is not None else None
        if found is None:
            return None
        ckpt, files, verified = found
        counters = rundir.parse_counters(ckpt, files["counters.json"])
        counters.setdefault("stage", 0)
        counters.setdefault("stat_totals", {})
        counters = {k: v for k, v in counters.items() if k in TrainState._fields[2:] and k not in SESSION_COUNTERS}
        try:
            template = like(counters)
            arrays = (template.params, template.opt_state)
            params, opt_state = eqx.tree_deserialise_leaves(io.BytesIO(files["state.eqx"]), arrays)
        except Exception as e:  # noqa: BLE001 — whatever the mismatch, one line
            why = "it was written by another version of the method" + (
                "" if verified else " (or is damaged: a checkpoint of an older physgrad has no checksums)"
            )
            raise ConfigError(f"the checkpoint {ckpt} does not match this method's state ({type(e).__name__}); "
                              f"{why}: delete {ckpt} to restart the run from step 0") from None  # fmt: skip
        return template._replace(params=params, opt_state=opt_state, **counters)


def finish(ending: Ending, *, recorder: Recorder, checkpointer: Checkpointer, budget: Budget) -> dict[str, Any]:
    """The final checkpoint, ``params.eqx``, ``test_cases.json`` and the summary (which the
    caller writes last: a run with a final ``summary.json`` has all its files). A run in
    memory writes none of them and returns the same summary."""
    state, setup, status, diverged_step = ending
    placement, run_dir = recorder.placement, checkpointer.run_dir
    checkpointer.save(state)
    rundir.fault("before-summary")
    params = state.params
    if checkpointer.writes and run_dir is not None:
        network = io.BytesIO()
        eqx.tree_serialise_leaves(network, setup.network(distributed.to_host(params)))
        rundir.atomic_write(run_dir / "params.eqx", network.getvalue())
    # Every test case's final metrics, for paired tests between methods (same seeds and cases).
    if run_dir is not None:  # every process evaluates (a collective under a mesh); process 0 writes
        with placement.scope():
            cases = distributed.to_host(make_evaluate(setup, per_sample=True)(params, recorder.splits["test"]))
        if checkpointer.writes:
            # one host copy per metric, then Python floats: iterating a JAX array compiles an
            # unstack with one output per case (1.6 s for 65,536 cases, in every process)
            write_json(
                run_dir / "test_cases.json",
                {k: np.asarray(vals, dtype=np.float64).tolist() for k, vals in cases.items()},
            )
    last = recorder.last
    summary = {
        "status": status,
        "budget": budget.to_dict(),
        "steps": state.step,
        "epochs": setup.epochs(state.step),
        "stage_steps": {
            s.label if len(setup.stages) == 1 else f"{i}:{s.label}": s.steps_done(state.step)
            for i, s in enumerate(setup.stages)
        },
        "train_seconds": state.train_time,
        "compile_seconds": state.compile_seconds,
        "time_per_step": state.train_time / state.step if state.step else None,
        # the same chunks on this process's CPU clock, over the steps this session took (the
        # calibration's cpu clock: harness.calibration.CLOCKS); None where it took none
        "cpu_seconds": state.cpu_seconds,
        "cpu_steps": state.cpu_steps,
        "cpu_time_per_step": state.cpu_seconds / state.cpu_steps if state.cpu_steps else None,
        "final_train_loss": last.get("train_loss"),
        "final_test_loss": last.get("test_loss"),
        "final_test_metrics": {k[5:]: v for k, v in last.items() if k.startswith("test_") and k != "test_loss"},
        "best_test_loss": state.best_test_loss if math.isfinite(state.best_test_loss) else None,
        "diverged_step": diverged_step,
        "last_finite_loss": state.last_finite_loss if status == "diverged" else None,
        "n_params": parameter_count(setup.params),
        "devices": distributed.mesh_size(placement.mesh),
        "solver_iterations": state.solver_iterations if recorder.fidelity.name else None,
        "prdp": state.prdp,
        "step_stat_totals": state.stat_totals,
    }
    return summary


# --- run directories -------------------------------------------------------------------------
# Every package whose version can change a run's numbers (None in env.json: not installed).
# exponax's steppers make the time-stepper data; optimistix and lineax solve SIP's inverses.
ENV_PACKAGES = ("physgrad", "jax", "jaxlib", "equinox", "optax", "numpy", "scipy", "jaxtyping", "lineax", "optimistix",
                "exponax", "kfac-jax", "phiflow", "phiml")  # fmt: skip


def environment() -> dict[str, Any]:
    """Versions, devices and thread pools (:func:`physgrad.cpu.report`: the command line's
    ``--threads`` setting and each pool's size), written as ``env.json``."""
    from importlib.metadata import PackageNotFoundError, version

    versions = {}
    for name in ENV_PACKAGES:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = None
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "devices": [str(d) for d in jax.devices()],
        "backend": jax.default_backend(),
        "x64": x64_enabled(),
        "versions": versions,
        "threads": cpu.report(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def write_json(path: Path, data: dict[str, Any]):
    """Write ``data`` as JSON all at once (:func:`physgrad.engine.rundir.atomic_write`)."""
    rundir.atomic_write(path, rundir.json_text(data))


def read_summary(run_dir: str | Path) -> dict[str, Any] | None:
    """A run's ``summary.json``, or None if it has none."""
    path = Path(run_dir) / "summary.json"
    return read_json(path) if path.exists() else None


def read_json(path: Path) -> dict[str, Any]:
    """A JSON object of the run directory; a damaged file is a one-line ConfigError."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path} cannot be read ({type(e).__name__}); the run directory is damaged: move it "
                          "away and run again") from None  # fmt: skip
    if not isinstance(data, dict):
        raise ConfigError(f"{path} is not a JSON object; the run directory is damaged: move it away and run again")
    return data


def is_complete(run_dir: str | Path) -> bool:
    """Whether a run finished or diverged (so a study can skip it). A finished summary
    without its final test loss (as an older physgrad wrote after resuming a finished run)
    is not complete: resuming finishes it again from its checkpoint."""
    summary = read_summary(run_dir)
    return summary is not None and is_final(summary)


def is_final(summary: dict[str, Any]) -> bool:
    """A final summary: diverged, or finished with its final losses."""
    if summary.get("status") not in FINAL_STATUSES:
        return False
    return summary["status"] == "diverged" or summary.get("final_test_loss") is not None


@contextlib.contextmanager
def writer_lock(run_dir: Path, placement: Placement):
    """The writer process locks the run directory (:func:`physgrad.engine.rundir.one_writer`); in a
    multi-process run every process learns whether it got the lock, so that none waits at a
    collective for a writer that was refused."""
    with contextlib.ExitStack() as stack:
        refused = None
        try:
            stack.enter_context(rundir.one_writer(run_dir, "run", enabled=placement.writer))
        except ConfigError as e:
            refused = e
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            flags = np.asarray(multihost_utils.process_allgather(np.array([int(refused is not None)])))
            if refused is None and flags.any():
                refused = ConfigError(f"the writer process could not lock {run_dir} (see its error)")
        if refused is not None:
            raise refused
        yield

"""The training engine: budgets, evaluation, checkpoints and run directories.

One run trains one method on one problem from one seed::

    data  = problem.make_data(fold_in(key(seed), 0))
    net   = problem.make_network(fold_in(key(seed), 1))
    loop: params, state, stats = step(params, state, train_data, order, batch_index)  # one jit
          every epoch (or ``eval_every`` steps): full train and test loss, not timed

A run directory holds ``config.json`` (the resolved :class:`~physgrad.config.RunConfig`),
``metrics.csv`` (long format: step, wall_time, split, metric, value), ``env.json``,
``summary.json``, ``params.eqx`` (the final network, Equinox serialisation) and
``checkpoint/`` (parameters, optimizer state and counters) for ``resume``.

Wall time counts training steps only: compilation (reported as ``compile_seconds``) and
evaluation are excluded, so equal budgets compare update rules, not tracing.
"""

from __future__ import annotations

import csv
import dataclasses
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
import jax.numpy as jnp
import numpy as np

from . import distributed
from . import prdp as prdp_control
from .config import ConfigError, RunConfig
from .nets import parameter_count
from .methods import METHODS, AbstractMethod, Objective
from .problems import PROBLEMS, AbstractProblem, ClosedLoopProblem, TimeStepperProblem
from .problems.direct import DirectOptimisation
from .progress import AbstractProgressMeter, NoProgressMeter

METRICS_HEADER = ("step", "wall_time", "split", "metric", "value")
FINAL_STATUSES = ("finished", "diverged")


@dataclasses.dataclass
class Stage:
    """One phase of a run, built: its method, batch size, length and first global step."""

    method: AbstractMethod
    batch_size: int
    steps_per_epoch: int
    start: int
    steps: int | None  # None: until the budget is spent
    label: str = ""  # the method's name (with the unroll length in a curriculum)

    def contains(self, step: int) -> bool:
        return step >= self.start and (self.steps is None or step < self.start + self.steps)

    def steps_done(self, step: int) -> int:
        """How many of the run's first ``step`` steps this stage took."""
        local = max(step - self.start, 0)
        return local if self.steps is None else min(local, self.steps)


@dataclasses.dataclass
class Setup:
    """Everything a run builds from its configuration before the first step."""

    problem: AbstractProblem
    data: dict[str, Any]
    params: Any
    static: Any
    objective: Objective
    stages: list[Stage]

    @property
    def method(self) -> AbstractMethod:
        """The first (for a single method: the only) stage's method."""
        return self.stages[0].method

    @property
    def steps_per_epoch(self) -> int:
        return self.stages[0].steps_per_epoch

    def stage_index(self, step: int) -> int:
        """The stage that takes global step ``step`` (0-based)."""
        return next(i for i, s in enumerate(self.stages) if s.contains(step))

    def epochs(self, step: int) -> float:
        """Epochs done after ``step`` steps (each stage counts its own batch size)."""
        return sum(s.steps_done(step) / s.steps_per_epoch for s in self.stages)

    def network(self, params=None):
        return eqx.combine(self.params if params is None else params, self.static)


def build(config: RunConfig, overrides: dict[str, Any] | None = None) -> Setup:
    """Problem, data, network and method(s) for a configuration (deterministic per seed).

    ``overrides`` replaces problem settings (a fidelity schedule such as PRDP changes the
    solver's iteration count during a run). A method with a curriculum (``stages()``)
    expands into one stage per curriculum step."""
    try:
        problem = PROBLEMS[config.problem](**{**config.problem_settings, **(overrides or {})})
    except ValueError as e:
        raise ConfigError(f"{config.problem}: {e}") from None
    key = jax.random.key(config.seed)
    if config.no_network:
        problem = DirectOptimisation(problem)
    try:
        data = problem.make_data(jax.random.fold_in(key, 0))
    except ValueError as e:
        raise ConfigError(f"{config.problem}: {e}") from None
    if config.no_network:
        network = problem.initial_network(data["train"])
    else:
        network = problem.make_network(jax.random.fold_in(key, 1))
    params, static = eqx.partition(network, eqx.is_inexact_array)
    n_train = jax.tree.leaves(data["train"])[0].shape[0]
    stages, start = [], 0
    for phase in config.phases:
        if phase.batch_size > n_train:
            raise ConfigError(f"batch_size {phase.batch_size} exceeds the {n_train} training samples")
        method = METHODS[phase.method](**phase.hyperparameters)
        per_epoch = n_train // phase.batch_size
        expanded = method.stages() if hasattr(method, "stages") else [(method, None)]
        phase_start = start
        for i, (stage_method, epochs) in enumerate(expanded):
            if epochs is not None:  # a curriculum stage before the last
                steps = max(1, round(epochs * per_epoch))
            elif phase.steps is not None:  # the phase's remaining steps
                steps = max(1, phase.steps - (start - phase_start))
            else:
                steps = None
            label = phase.method + (f"[m={stage_method.m}]" if len(expanded) > 1 else "")
            stages.append(Stage(stage_method, phase.batch_size, per_epoch, start, steps, label))
            start += steps or 0

    def predict(p, sample):
        return problem.predict(eqx.combine(p, static), sample)

    def network_output(p, sample):
        return problem.network_output(eqx.combine(p, static), sample)

    objective = Objective(
        predict,
        problem.loss,
        network_output=network_output,
        simulate=problem.simulate,
        target=problem.target,
        inverse=problem.inverse,
        rollout=_rollout_system(problem, static),
        unrolled=_unrolled_system(problem, static),
    )
    opaque = isinstance(problem, TimeStepperProblem) and objective.unrolled(None, False).differentiable_physics is False
    for phase in config.phases:
        method = METHODS[phase.method](**phase.hyperparameters)
        try:
            method.check(objective)
            method.check_batch_size(phase.batch_size)
            if opaque and not hasattr(method, "policy"):  # open-loop methods back-propagate through everything
                raise ValueError("this method differentiates through the solver, which is not differentiable; use nog or one")
        except ValueError as e:
            raise ConfigError(f"{phase.method} on {config.problem}: {e}") from None
    return Setup(problem=problem, data=data, params=params, static=static, objective=objective, stages=stages)


def _rollout_system(problem: AbstractProblem, static):
    """The rollout system of a closed-loop or time-stepper problem (None for open-loop ones)."""
    if isinstance(problem, ClosedLoopProblem):
        return problem.system(lambda p, s: problem.control(eqx.combine(p, static), s))
    if isinstance(problem, TimeStepperProblem):
        return _unrolled_system(problem, static)(None, False)
    return None


def _unrolled_system(problem: AbstractProblem, static):
    """``(m, teacher_forcing) -> System`` of a time-stepper problem (None otherwise)."""
    if not isinstance(problem, TimeStepperProblem):
        return None

    def apply(p, u, cond):
        return problem.apply(eqx.combine(p, static), u, cond)

    return lambda m=None, teacher_forcing=False: problem.system(apply, m, teacher_forcing)


def _refinable(config: RunConfig) -> str | None:
    """The problem setting a fidelity schedule refines (None if the problem has none);
    a one-line error if PRDP is asked for on a problem without one."""
    name = getattr(PROBLEMS[config.problem], "refinable_setting", None)
    if config.prdp and name is None:
        valid = [n for n, c in PROBLEMS.items() if getattr(c, "refinable_setting", None)]
        raise ConfigError(f"prdp needs a problem with an iterative solver; valid choices: {', '.join(valid)}")
    if config.prdp and config.problem_settings.get("setup") == "prediction":
        raise ConfigError("prdp refines the solver of a correction setup; use setup=correction")
    if config.prdp and (config.prdp_start < 1 or config.prdp_increment < 1):
        raise ConfigError("prdp_start and prdp_increment must be >= 1")
    if config.prdp and not (0 < config.prdp_tau_stop <= 1 and 0 < config.prdp_tau_step <= 1):
        raise ConfigError("prdp_tau_step and prdp_tau_stop must be in (0, 1]")
    return name


def _refine(setup: Setup, rebuilt: Setup) -> Setup:
    """``setup`` with the problem and objective of ``rebuilt`` (another solver fidelity);
    the network, data and stages stay."""
    return dataclasses.replace(setup, problem=rebuilt.problem, objective=rebuilt.objective)


def make_step(setup: Setup, batch_size: int, method: AbstractMethod | None = None):
    """The training step as one jitted function of (params, state, data, order, index).

    The mini-batch is gathered inside the jit (``order`` is the epoch's sample order,
    ``index`` the batch number), so a step is a single dispatch with no host work.
    ``method`` defaults to the first stage's.

    Traced under a mesh (``jax.set_mesh``, see :mod:`physgrad.distributed`), the batch
    is split over the mesh's ``"data"`` axis and parameters and state stay replicated:
    data-parallel training with the single-device update.
    """
    method = method or setup.method

    def step(params, state, data, order, index):
        rows = jax.lax.dynamic_slice_in_dim(order, index * batch_size, batch_size)
        batch = distributed.shard_batch(jax.tree.map(lambda a: a[rows], data))
        params, state, stats = method.step(setup.objective, params, state, batch)
        return distributed.replicated(params), distributed.replicated(state), stats

    return jax.jit(step)


def make_evaluate(setup: Setup, chunk: int = 1024, per_sample: bool = False):
    """Mean per-sample loss and the problem's extra metrics over a data split (jitted, in
    chunks of ``chunk``): ``{"loss": ..., **problem.metrics}``; with ``per_sample`` the
    values of every sample instead of their means (for paired tests across methods).
    Traced under a mesh, the samples are split over its devices."""
    problem = setup.problem

    def one(params, sample):
        x = problem.network_output(setup.network(params), sample)
        y = problem.simulate(x, sample)
        return {"loss": problem.loss(y, sample), **problem.metrics(x, y, sample)}

    def evaluate(params, data):
        return distributed.replicated(split_evaluate(params, data))  # whole on every device

    def split_evaluate(params, data):
        n = jax.tree.leaves(data)[0].shape[0]
        devices = distributed.data_axis_size()
        if devices == 1:
            values = jax.lax.map(lambda s: one(params, s), data, batch_size=min(chunk, n))
        else:  # each device evaluates its share: (devices, n/devices) with the first axis split
            pad = -n % devices  # repeats of the last sample, cut off again below
            data = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), data)
            data = jax.tree.map(lambda a: a.reshape(devices, (n + pad) // devices, *a.shape[1:]), data)
            data = distributed.shard_batch(data)
            per_device = min(chunk, (n + pad) // devices)
            values = jax.vmap(lambda d: jax.lax.map(lambda s: one(params, s), d, batch_size=per_device))(data)
            values = jax.tree.map(lambda v: v.reshape(n + pad, *v.shape[2:])[:n], values)
        return values if per_sample else jax.tree.map(jnp.mean, values)

    return jax.jit(evaluate)


def environment() -> dict[str, Any]:
    """Versions and devices, written as ``env.json``."""
    from importlib.metadata import PackageNotFoundError, version

    versions = {}
    for name in ("physgrad", "jax", "jaxlib", "equinox", "optax", "numpy"):
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
        "x64": bool(jax.config.jax_enable_x64),
        "versions": versions,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


class MetricsLog:
    """Appends long-format rows to ``metrics.csv``; on resume, drops rows after the checkpoint."""

    def __init__(self, path: Path, keep_until_step: int | None = None, enabled: bool = True):
        self.path = path
        self.enabled = enabled
        if not enabled:
            return
        rows = []
        if keep_until_step is not None and path.exists():
            with path.open() as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= keep_until_step]
        with path.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(METRICS_HEADER)
            writer.writerows([[r[k] for k in METRICS_HEADER] for r in rows])

    def write(self, step: int, wall_time: float, values: dict[tuple[str, str], float]):
        if not self.enabled:
            return
        with self.path.open("a", newline="") as f:
            writer = csv.writer(f)
            for (split, metric), value in values.items():
                writer.writerow([step, f"{wall_time:.6f}", split, metric, repr(float(value))])


def read_metrics(path: Path) -> list[dict[str, Any]]:
    """``metrics.csv`` as a list of typed rows."""
    with Path(path).open() as f:
        return [
            {
                "step": int(r["step"]),
                "wall_time": float(r["wall_time"]),
                "split": r["split"],
                "metric": r["metric"],
                "value": float(r["value"]),
            }
            for r in csv.DictReader(f)
        ]


def _write_json(path: Path, data: dict[str, Any]):
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")
    os.replace(tmp, path)


def _save_checkpoint(run_dir: Path, params, state, counters: dict[str, Any]):
    ckpt = run_dir / "checkpoint"
    ckpt.mkdir(exist_ok=True)
    tmp = ckpt / "state.eqx.tmp"
    eqx.tree_serialise_leaves(tmp, (params, state))
    os.replace(tmp, ckpt / "state.eqx")
    _write_json(ckpt / "counters.json", counters)


def _load_checkpoint(run_dir: Path, like: Callable[[dict[str, Any]], Any]):
    """Counters, then (params, state) shaped as ``like(counters)`` (the state's structure
    depends on the stage the checkpoint was taken in)."""
    ckpt = run_dir / "checkpoint"
    counters = json.loads((ckpt / "counters.json").read_text())
    counters.setdefault("stage", 0)
    counters.setdefault("stat_totals", {})
    params, state = eqx.tree_deserialise_leaves(ckpt / "state.eqx", like(counters))
    return params, state, counters


def load_network(run_dir: str | Path):
    """The final trained network of a run directory (``params.eqx``)."""
    run_dir = Path(run_dir)
    config = RunConfig.from_dict(json.loads((run_dir / "config.json").read_text()))
    setup = build(config)
    return eqx.tree_deserialise_leaves(run_dir / "params.eqx", setup.network())


def _clock_of_process_0(seconds: float) -> float:
    """Process 0's training time on every process (one small collective per step), so that
    seconds budgets and ``eval_seconds`` stop and evaluate all processes at the same step."""
    from jax.experimental import multihost_utils

    return float(multihost_utils.broadcast_one_to_all(np.float64(seconds)))


def _same_run(a: RunConfig, b: RunConfig) -> bool:
    strip = lambda c: {k: v for k, v in c.canonical_dict().items() if k != "budget"}  # noqa: E731
    return strip(a) == strip(b)


def train(
    config: RunConfig,
    run_dir: str | Path,
    *,
    resume: bool = False,
    progress: AbstractProgressMeter | None = None,
    devices: int | str | None = 1,
) -> dict[str, Any]:
    """Train one run into ``run_dir`` and return its summary (also ``summary.json``).

    With ``resume=True`` an existing run continues from its last checkpoint up to
    ``config.budget`` (which may be larger than the original one); a finished run whose
    budget is already met returns its summary unchanged. A run whose loss turns NaN or
    infinite stops with status ``"diverged"``, the step and the last finite loss.

    ``devices`` (a number or ``"all"``) splits every batch over that many devices
    (:mod:`physgrad.distributed`); the updates equal the single-device ones to float
    tolerance. In a multi-process run every process calls ``train`` alike and only
    process 0 writes ``run_dir`` (on several hosts it must be a shared file system for
    ``resume``).
    """
    run_dir = Path(run_dir)
    progress = progress or NoProgressMeter()
    mesh = distributed.make_mesh(devices)
    writer = distributed.is_writer()
    config_path = run_dir / "config.json"
    if config_path.exists():
        if not resume:
            raise ConfigError(f"run directory {run_dir} exists; pass --resume or choose another --out")
        old = RunConfig.from_dict(json.loads(config_path.read_text()))
        if not _same_run(old, config):
            raise ConfigError(f"run directory {run_dir} holds a different configuration; choose another --out")
    has_ckpt = resume and (run_dir / "checkpoint" / "counters.json").exists()
    if jax.process_count() > 1:  # every process has looked at run_dir before process 0 writes to it
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(f"physgrad.train:{run_dir}")
    if not writer:  # other processes compute alike and write nothing
        progress = NoProgressMeter()
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
    done = read_summary(run_dir) if has_ckpt else None
    # Nothing to do (checked before building data and network): diverged, or finished on this budget.
    if done and (
        done["status"] == "diverged" or (done["status"] == "finished" and done.get("budget") == config.budget.to_dict())
    ):
        return done

    refinable = _refinable(config)
    setup = build(config)
    for stage in setup.stages:
        distributed.check_batch(stage.batch_size, mesh)
    full_fidelity = getattr(setup.problem, refinable) if refinable else None
    counters = {
        "step": 0, "stage": 0, "train_time": 0.0, "compile_seconds": 0.0, "best_test_loss": math.inf,
        "stat_totals": {},  # sums over all steps of the methods' extra step statistics
        "solver_iterations": 0,  # Σ over steps of the solver's inner iteration count
    }  # fmt: skip
    if config.prdp:
        counters["prdp"] = prdp_control.initial_state(min(config.prdp_start, full_fidelity))
    params = setup.params
    if has_ckpt:
        like = lambda c: (params, setup.stages[c["stage"]].method.init(params))  # noqa: E731
        params, state, counters = _load_checkpoint(run_dir, like)
    else:
        state = setup.stages[0].method.init(params)
    if jax.process_count() > 1:  # every process must resume from the same checkpoint
        from jax.experimental import multihost_utils

        seen = multihost_utils.process_allgather(np.array([int(has_ckpt), counters["step"]]))
        if len({tuple(row) for row in np.asarray(seen).reshape(-1, 2)}) > 1:
            raise ConfigError(f"the processes see different checkpoints in {run_dir}; a multi-process --resume "
                              "needs --out on a file system every process shares")  # fmt: skip
    if config.prdp:
        setup = _refine(setup, build(config, {refinable: counters["prdp"]["K"]}))
    if writer:
        _write_json(config_path, config.to_dict())
        _write_json(run_dir / "env.json", {**environment(), "mesh_devices": distributed.mesh_size(mesh)})
    log = MetricsLog(run_dir / "metrics.csv", keep_until_step=counters["step"] if has_ckpt else None, enabled=writer)

    budget = config.budget
    train_data, test_data = setup.data["train"], setup.data["test"]
    n_train = jax.tree.leaves(train_data)[0].shape[0]
    shuffle_key = jax.random.fold_in(jax.random.key(config.seed), 2)
    evaluate = make_evaluate(setup)

    def order_for(stage: int, epoch: int):
        if config.shuffle:
            key = jax.random.fold_in(jax.random.fold_in(shuffle_key, stage), epoch)
            order = jax.random.permutation(key, n_train).astype(jnp.int32)
        else:
            order = jnp.arange(n_train, dtype=jnp.int32)
        return distributed.replicate(order, mesh)

    def budget_met(step: int, train_time: float) -> bool:
        if budget.kind == "seconds":
            return train_time >= budget.amount
        if budget.kind == "steps":
            return step >= budget.amount
        return setup.epochs(step) >= budget.amount - 1e-9

    def stage_end(step: int) -> bool:
        current = setup.stages[counters["stage"]]
        return current.steps is not None and step == current.start + current.steps

    def next_eval_time(train_time: float) -> float:
        return config.eval_seconds * (1 + math.floor(train_time / config.eval_seconds))

    next_eval = [next_eval_time(counters["train_time"])] if config.eval_seconds > 0 else None

    def eval_due(step: int, train_time: float) -> bool:
        """Every ``eval_seconds`` of training time if set (equal points per curve in a
        wall-clock comparison), else every ``eval_every`` steps, else every epoch of the
        current stage; always at the end of a stage and of the budget."""
        if budget_met(step, train_time) or stage_end(step):
            return True
        if next_eval is not None:
            if train_time < next_eval[0]:
                return False
            next_eval[0] = next_eval_time(train_time)
            return True
        if config.eval_every:
            return step % config.eval_every == 0
        current = setup.stages[counters["stage"]]
        return (step - current.start) % current.steps_per_epoch == 0

    def compile_stage(index: int):
        current = setup.stages[index]
        fn = make_step(setup, current.batch_size, current.method)
        t0 = time.perf_counter()
        with distributed.use_mesh(mesh):
            compiled = fn.lower(params, state, train_data, order_for(index, 0), np.int32(0)).compile()
        counters["compile_seconds"] += time.perf_counter() - t0
        return compiled

    step, train_time = counters["step"], counters["train_time"]
    status, diverged_step, last_finite = "running", None, None
    last_eval: dict[str, float] = {}
    window: dict[str, tuple[float, int]] = {}
    # The train-split evaluation may be limited to its first eval_samples samples (large
    # image datasets would otherwise cost more per evaluation than many training steps).
    n_eval = config.eval_samples or getattr(setup.problem, "default_eval_samples", 0) or None
    # A problem's own default takes a strided subset: its windows are stored trajectory by
    # trajectory, so the first N would all come from one trajectory.
    stride = max(1, n_train // n_eval) if n_eval and not config.eval_samples else 1
    eval_train = distributed.replicate(jax.tree.map(lambda a: a[::stride][:n_eval], train_data), mesh)
    # Under a mesh every array a step sees lives on all its devices (every process holds
    # the same seed-generated values).
    train_data, test_data = distributed.replicate((train_data, test_data), mesh)
    val_data = distributed.replicate(setup.data.get("val"), mesh)
    params, state = distributed.replicate((params, state), mesh)

    def record(step: int, train_time: float) -> bool:
        """Full-set losses and metrics at this step; returns False if a loss is not finite."""
        values = {}
        # The methods' extra per-step statistics (SIP's proxy loss and inverse failures),
        # averaged over the steps since the last evaluation: split "train", metric "step_<name>".
        for name, (total, count) in window.items():
            values[("train", f"step_{name}")] = total / count
        window.clear()
        for split, split_data in (("train", eval_train), ("test", test_data)):
            with distributed.use_mesh(mesh):
                evaluated = evaluate(params, split_data)
            for metric, value in evaluated.items():
                values[(split, metric)] = float(value)
        if step > 0:
            values[("train", "time_per_step")] = train_time / step
        if refinable:
            values[("train", "solver_iterations")] = iterations_now()
        if val_data is not None:  # the validation split (PRDP's decisions, and its baselines)
            with distributed.use_mesh(mesh):
                val = evaluate(params, val_data)
            error = float(val.get("rel_error", val["loss"]))
            for metric, value in val.items():
                values[("val", metric)] = float(value)
        if config.prdp and not budget_met(step, train_time):
            counters["prdp"] = prdp_control.update(
                counters["prdp"], error, step, increment=config.prdp_increment, maximum=full_fidelity,
                tau_step=config.prdp_tau_step, tau_stop=config.prdp_tau_stop,
            )  # fmt: skip
        log.write(step, train_time, values)
        last_eval.update({f"{split}_{metric}": v for (split, metric), v in values.items()})
        if math.isfinite(last_eval["test_loss"]):
            counters["best_test_loss"] = min(counters["best_test_loss"], last_eval["test_loss"])
        return math.isfinite(last_eval["train_loss"]) and math.isfinite(last_eval["test_loss"])

    def iterations_now() -> int:
        return counters["prdp"]["K"] if config.prdp else full_fidelity

    def checkpoint():
        counters.update(step=step, train_time=train_time)
        if writer:
            _save_checkpoint(run_dir, *distributed.to_host((params, state)), counters)

    if step == 0:
        record(0, 0.0)
    last_ckpt_time = train_time
    progress.start(
        budget=budget, steps_per_epoch=setup.steps_per_epoch, step=step, train_time=train_time, label=run_dir.name
    )
    compiled = compile_stage(counters["stage"])
    order, order_epoch = None, None
    try:
        while not budget_met(step, train_time):
            index = setup.stage_index(step)
            if index != counters["stage"]:
                # Switch method: the parameters carry over exactly, the new method starts fresh.
                counters["stage"] = index
                state = distributed.replicate(setup.stages[index].method.init(distributed.to_host(params)), mesh)
                compiled = compile_stage(index)
            current = setup.stages[index]
            epoch, batch = divmod(step - current.start, current.steps_per_epoch)
            if (index, epoch) != order_epoch:
                order, order_epoch = order_for(index, epoch), (index, epoch)
            t_start = time.perf_counter()
            new_params, new_state, stats = compiled(params, state, train_data, order, np.int32(batch))
            loss = float(stats["loss"])  # waits for the step: the timing is honest
            train_time += time.perf_counter() - t_start
            if jax.process_count() > 1:  # process 0's clock decides budgets and evaluations for all
                train_time = _clock_of_process_0(train_time)
            if not math.isfinite(loss) and not float(stats.get("skipped", 0.0)):
                status, diverged_step = "diverged", step
                break
            params, state = new_params, new_state
            last_finite = loss if math.isfinite(loss) else last_finite
            if refinable:
                counters["solver_iterations"] += iterations_now()
            for name, value in stats.items():
                if name != "loss":
                    value = float(value)
                    if not math.isfinite(value):  # e.g. the norm of a skipped NaN gradient
                        continue
                    total, count = window.get(name, (0.0, 0))
                    window[name] = (total + value, count + 1)
                    counters["stat_totals"][name] = counters["stat_totals"].get(name, 0.0) + value
            step += 1
            if eval_due(step, train_time):
                k_before = iterations_now() if refinable else None
                if not record(step, train_time):
                    status, diverged_step = "diverged", step
                    break
                if config.prdp and iterations_now() != k_before:  # PRDP refined: rebuild the solver
                    setup = _refine(setup, build(config, {refinable: iterations_now()}))
                    evaluate = make_evaluate(setup)
                    compiled = compile_stage(counters["stage"])
            if train_time - last_ckpt_time >= config.checkpoint_seconds:
                checkpoint()
                last_ckpt_time = train_time
            progress.update(step=step, train_time=train_time, loss=loss)
    except KeyboardInterrupt:
        checkpoint()
        if writer:
            _write_json(run_dir / "summary.json", {"status": "interrupted", "steps": step, "train_seconds": train_time})
        raise
    finally:
        progress.close()

    if status == "running":
        status = "finished"
    checkpoint()
    if writer:
        eqx.tree_serialise_leaves(run_dir / "params.eqx", setup.network(distributed.to_host(params)))
    # Every test case's final metrics, for paired tests between methods (same seeds and cases).
    with distributed.use_mesh(mesh):
        cases = distributed.to_host(make_evaluate(setup, per_sample=True)(params, test_data))
    if writer:
        _write_json(run_dir / "test_cases.json", {k: [float(v) for v in vals] for k, vals in cases.items()})
    summary = {
        "status": status,
        "problem": config.problem,
        "method": config.method,
        "seed": config.seed,
        "budget": budget.to_dict(),
        "steps": step,
        "epochs": setup.epochs(step),
        "stage_steps": {
            s.label if len(setup.stages) == 1 else f"{i}:{s.label}": s.steps_done(step)
            for i, s in enumerate(setup.stages)
        },
        "train_seconds": train_time,
        "compile_seconds": counters["compile_seconds"],
        "time_per_step": train_time / step if step else None,
        "final_train_loss": last_eval.get("train_loss"),
        "final_test_loss": last_eval.get("test_loss"),
        "final_test_metrics": {k[5:]: v for k, v in last_eval.items() if k.startswith("test_") and k != "test_loss"},
        "best_test_loss": counters["best_test_loss"] if math.isfinite(counters["best_test_loss"]) else None,
        "diverged_step": diverged_step,
        "last_finite_loss": last_finite if status == "diverged" else None,
        "n_params": parameter_count(setup.params),
        "devices": distributed.mesh_size(mesh),
        "solver_iterations": counters["solver_iterations"] if refinable else None,
        "prdp": counters.get("prdp"),
        "step_stat_totals": counters["stat_totals"],
    }
    if writer:
        _write_json(run_dir / "summary.json", summary)
    return summary


def read_summary(run_dir: str | Path) -> dict[str, Any] | None:
    """A run's ``summary.json``, or None if it has none."""
    path = Path(run_dir) / "summary.json"
    return json.loads(path.read_text()) if path.exists() else None


def is_complete(run_dir: str | Path) -> bool:
    """Whether a run finished or diverged (so a study can skip it)."""
    summary = read_summary(run_dir)
    return summary is not None and summary.get("status") in FINAL_STATUSES


__all__ = ["Setup", "build", "load_network", "make_evaluate", "make_step", "read_metrics", "train"]

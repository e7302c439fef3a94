"""Tuning each method on equal trials (Optuna), selected on validation, reported on test.

``physgrad tune PROBLEM --methods a,b --trials N --seconds S`` and :func:`tune` follow
AlgoPerf's external-tuning rules (Dahl et al. 2023, §4): every method gets the same number
of trials, drawn quasi-randomly from its declared search space
(:mod:`physgrad.harness.spaces`), each trial an ordinary physgrad run on the same
calibrated budget; the configuration with the lowest final **validation** loss is chosen
and re-run on ≥ 3 seeds, reported on **test**.

- **Trials.** Optuna (Akiba et al. 2019) holds the studies, one per method, named
  ``PROBLEM:METHOD``; the sampler is ``optuna.samplers.QMCSampler`` (scrambled Sobol,
  seeded), so a trial's point depends on its number only. Trial 0 is the untuned
  configuration (the paper's defaults), so tuning never selects worse than untuned on
  validation. It runs first, alone per method (QMC learns the space from a finished
  trial), then the other trials in parallel on the executor
  (:mod:`physgrad.harness.workers`): the same points, the same numbers with 1 or N workers.
- **Validation.** Trials run with :class:`physgrad.HoldOut` as :func:`physgrad.fit`'s
  ``split``: the problem's ``val`` split where it has one, else the last ``holdout`` of
  train, held out; the test split never reaches a trial (a trial directory's "test"
  curves are validation curves).
- **Budget.** A seconds budget is calibrated once per method on its untuned step
  (``calibration.json``; the searched settings do not change a step's cost), so every trial
  of a method trains the same number of steps.
- **Pruning** (optional, :class:`SuccessiveHalving`; Jamieson & Talwalkar 2016, Li et al.
  2018): rung by rung, all trials after trial 0 train to a fraction of the steps, the best
  1/η go on (resumed from their checkpoints to the larger budget), the others are pruned.
- **Storage.** An Optuna journal file ``DIR/optuna.journal`` by default (appends under a
  file lock: safe for many local processes, survives kill -9), or any Optuna storage URL
  (``postgresql://user@host/db`` for many machines). A killed tune runs again with the same
  command: finished trials are kept, interrupted ones resume from their run's checkpoint.
- **Files.** ``tune.json`` (what was asked, the spaces), ``trials/METHOD/trialNNN/`` (run
  directories), ``trials.csv`` (every trial: state, validation loss, hyperparameters),
  ``best.json`` and ``final/`` (an ordinary study directory of the chosen configurations
  on the seeds: ``physgrad report DIR/final``). ``physgrad report DIR`` draws each
  method's trials, score against each hyperparameter (:mod:`physgrad.harness.tune_report`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from ..engine import Budget, HoldOut, TrainSettings, rundir
from ..engine.types import Seconds, Steps
from ..errors import ConfigError
from .spaces import Space, describe_space, distributions
from .tune_storage import default_sampler, open_storage
from .workers import AbstractExecutor, ConfiguredRun, ObjectRun, executor_for, run_directory

TRIAL_COLUMNS = ("method", "trial", "state", "val_loss", "steps", "run_dir", "params")


@dataclasses.dataclass(frozen=True)
class NoPruning:
    """Every trial trains its full budget."""

    def rungs(self, steps: int) -> list[int]:
        return [steps]


@dataclasses.dataclass(frozen=True)
class SuccessiveHalving:
    """Synchronous successive halving over ``rungs`` budgets steps/η^(rungs−1), …, steps/η,
    steps: after each rung the best ⌈n/η⌉ trials go on. Synchronous (each rung waits for
    all its trials), so the pruned set does not depend on which worker finished first."""

    eta: int = 3
    rungs_count: int = 3

    def __post_init__(self):
        if self.eta < 2 or self.rungs_count < 1:
            raise ConfigError(f"successive halving needs eta >= 2 and rungs >= 1, got {self.eta}, {self.rungs_count}")

    def rungs(self, steps: int) -> list[int]:
        out = [max(1, steps // self.eta ** (self.rungs_count - 1 - r)) for r in range(self.rungs_count)]
        return sorted(set(out))


class TuneResult(NamedTuple):
    """What :func:`tune` chose and measured: ``best`` {method: hyperparameters}, every trial
    (``trials``: rows of ``trials.csv``) and the chosen configurations' test runs
    (``final``: summary rows, one per method × seed)."""

    best: dict[str, dict[str, Any]]
    trials: list[dict[str, Any]]
    final: list[dict[str, Any]]


@dataclasses.dataclass
class _Method:
    """One method's tuning: its untuned run, its space, its Optuna study and trial budget."""

    name: str
    defaults: dict[str, Any]  # the untuned hyperparameters
    space: dict[str, Any]  # optuna distributions
    steps: int | None  # the trial budget in steps (None: ``budget`` as given)
    make: Callable[[dict[str, Any], int | None, str], Any]  # (params, steps, run_dir) -> job
    study: Any = None


def tune(
    problem: Any,
    methods: Sequence[str],
    *,
    trials: int = 5,
    budget: Budget,
    out: str | Path,
    seeds: int = 3,
    settings: dict[str, Any] | None = None,
    spaces: Mapping[str, Space] | None = None,
    sampler: Callable[[], Any] | None = None,
    pruning: NoPruning | SuccessiveHalving = NoPruning(),
    storage: Any = None,
    executor: AbstractExecutor | None = None,
    seed: int = 0,
    holdout: float = 0.2,
    echo: Callable[[str], None] = print,
) -> TuneResult:
    """Tune ``methods`` on ``problem`` with ``trials`` trials each and report the chosen
    configurations on test (see the module docstring).

    ``problem`` is a registered name (``"sine"``; ``settings`` are ``--set`` values, scoped
    ``hig.lr=...`` allowed) or your own :class:`~physgrad.AbstractProblem` object (then
    ``settings`` may hold ``batch_size``/``METHOD.batch_size`` and the
    :class:`~physgrad.TrainSettings` fields; a seconds budget needs a registered problem's
    calibration: give steps or epochs). ``spaces`` replaces methods' declared spaces;
    ``sampler`` makes a sampler per method (default :func:`default_sampler` of ``seed``);
    ``storage`` an Optuna storage or URL (default the journal in ``out``); ``executor``
    where the runs go (default: in this process; :func:`physgrad.harness.workers.executor_for`).
    Trials train with seed ``seed``; the chosen configurations with seeds 0..seeds−1."""
    import optuna

    if trials < 1 or seeds < 1:
        raise ConfigError(f"trials and seeds must be at least 1, got {trials} and {seeds}")
    try:
        split = HoldOut(holdout)  # every trial's data: validation in place of test
    except ValueError as e:
        raise ConfigError(str(e)) from None
    out = Path(out)
    owned = executor is None
    executor = executor or executor_for(1)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        with rundir.one_writer(out, "tune"):
            plans = _plan(problem, methods, budget, out, settings or {}, spaces, split, seed, echo)
            store = open_storage(out, storage)
            name = problem if isinstance(problem, str) else problem.name
            for m in plans:
                m.study = optuna.create_study(study_name=f"{name}:{m.name}", storage=store, direction="minimize",
                                              sampler=(sampler or (lambda: default_sampler(seed)))(),
                                              load_if_exists=True)  # fmt: skip
            rundir.atomic_write(out / "tune.json", json.dumps({
                "problem": name, "methods": [m.name for m in plans], "trials": trials, "budget": budget.to_dict(),
                "seeds": seeds, "settings": settings or {}, "seed": seed, "holdout": holdout,
                "pruning": dataclasses.asdict(pruning) | {"kind": type(pruning).__name__},
                "storage": "journal" if storage is None else "url" if isinstance(storage, str) else "object",
                "spaces": {m.name: describe_space(m.name, m.defaults, spaces) for m in plans},
                "bounds": {m.name: {k: [d.low, d.high] for k, d in m.space.items()} for m in plans},
                "defaults": {m.name: {k: m.defaults[k] for k in m.space} for m in plans},
                "trial_steps": {m.name: m.steps for m in plans},
            }, indent=2, default=str) + "\n")  # fmt: skip
            _run_trials(plans, trials, pruning, executor, out, echo)
            rows = write_trials(out, plans)
            best = {m.name: _best(m) for m in plans}
            rundir.atomic_write(out / "best.json", json.dumps(best, indent=2) + "\n")
        final = _final(problem, plans, best, budget, seeds, out / "final", settings or {}, executor, echo)
        return TuneResult(best, rows, final)
    finally:
        if owned:
            executor.close()


# --- planning -----------------------------------------------------------------------------------
def _plan(problem, methods, budget, out, settings, spaces, split, seed, echo) -> list[_Method]:
    if not methods:
        raise ConfigError("tune needs at least one method")
    if isinstance(problem, str):
        return _plan_registered(problem, list(methods), budget, out, settings, spaces, split, seed, echo)
    return _plan_object(problem, list(methods), budget, settings, spaces, split, seed)


def _plan_registered(problem, methods, budget, out, settings, spaces, split, seed, echo) -> list[_Method]:
    from .calibration import study_calibration
    from .config import make_config
    from .study import calibrated_config, plan

    configs = plan(problem, methods, [seed], budget, settings)  # every name and setting checked first
    calibration = None
    if isinstance(budget, Seconds):
        # a method whose step cannot be built (a crash, the memory guard) is left out with its
        # reason, and the others are tuned: a bench over many methods goes on (failures.recordable)
        calibration = study_calibration(out, {c.method: c for c in configs}, echo=echo, record_failures=True)
        for config in configs:
            if (error := calibration.error(config.method)) is not None:
                echo(f"{config.method}: left out of the tuning, its step could not be built ({error})")
        configs = [c for c in configs if calibration.error(c.method) is None]
    plans = []
    for config in configs:
        defaults = dict(config.phases[0].hyperparameters)

        def make(params, steps, run_dir, config=config):
            from .study import settings_for

            scoped = {**settings_for(problem, config.method, methods, settings),
                      **{f"{config.method}.{k}": v for k, v in params.items()}}  # fmt: skip
            c = make_config(problem, config.method, budget=budget, seed=seed, settings=scoped)
            if calibration is not None:
                c = calibrated_config(c, calibration, float(budget.amount))
            if steps is not None:
                c = dataclasses.replace(c, budget=Steps(steps))
            return ConfiguredRun(c, run_dir, split=split)

        steps = calibration.steps(config.method, float(budget.amount)) if calibration is not None else (
            budget.amount if isinstance(budget, Steps) else None)  # fmt: skip
        plans.append(_Method(config.method, defaults, distributions(config.method, defaults, spaces), steps, make))
    return plans


def object_settings(problem, method: str, settings: dict[str, Any]) -> tuple[int, TrainSettings]:
    """A user's problem object's run settings for ``method``: the batch size
    (``METHOD.batch_size``, ``batch_size``, else the problem's default) and the
    :class:`~physgrad.TrainSettings` fields among ``settings``."""
    fields = {f.name for f in dataclasses.fields(TrainSettings)}
    known = fields | {"batch_size"}
    for key in settings:
        if key.rpartition(".")[2] not in known:
            raise ConfigError(
                f"unknown setting {key!r} for a problem object; valid choices: {', '.join(sorted(known))}"
            )
    batch = settings.get(f"{method}.batch_size", settings.get("batch_size", problem.default_batch_size))
    train = {k: settings[k] for k in fields if k in settings}
    return int(batch), TrainSettings(**train)


def _plan_object(problem, methods, budget, settings, spaces, split, seed) -> list[_Method]:
    from .registry import METHODS, hyperparameters

    if isinstance(budget, Seconds):
        raise ConfigError("a problem object is tuned on a steps or epochs budget (a seconds budget is calibrated "
                          "from a registered problem's configuration): Steps(N)")  # fmt: skip
    plans = []
    for method in methods:
        if method not in METHODS:  # an import path's or a plugin's own line where it has one
            raise ConfigError(METHODS.why_not(method) or f"unknown method {method!r}; valid choices: {', '.join(METHODS)}")  # fmt: skip
        defaults = hyperparameters(method)
        defaults.update({k.partition(".")[2]: v for k, v in settings.items() if k.startswith(f"{method}.")
                         and k.partition(".")[2] in defaults})  # fmt: skip
        batch, train = object_settings(problem, method, settings)

        def make(params, steps, run_dir, method=method, defaults=defaults, batch=batch, train=train):
            run_budget = Steps(steps) if steps is not None else budget
            return ObjectRun(problem, method, {**defaults, **params}, batch, seed, run_budget, run_dir, train,
                             split=split)  # fmt: skip

        steps = budget.amount if isinstance(budget, Steps) else None
        plans.append(_Method(method, defaults, distributions(method, defaults, spaces), steps, make))
    return plans


# --- trials -----------------------------------------------------------------------------------------
def trial_dir(out: Path, method: str, number: int) -> str:
    from .config import method_slug

    return run_directory(out / "trials" / method_slug(method) / f"trial{number:03d}")


def _run_trials(plans: list[_Method], trials: int, pruning, executor: AbstractExecutor, out: Path, echo) -> None:
    """Trial 0 of every method first (alone per method), then the rest; trials of an earlier,
    interrupted tune (RUNNING in the storage) are run again, resuming their runs."""
    import optuna

    first, rest = [], []
    for m in plans:
        done = m.study.get_trials(deepcopy=False)
        stale = [t for t in done if t.state == optuna.trial.TrialState.RUNNING and set(t.params) == set(m.space)]
        for t in done:  # a trial cut off before its point was stored cannot be run: failed
            if t.state == optuna.trial.TrialState.RUNNING and t not in stale:
                m.study.tell(t.number, state=optuna.trial.TrialState.FAIL)
        targets = [(m, optuna.trial.Trial(m.study, t._trial_id)) for t in stale]
        if not done:
            m.study.enqueue_trial({k: _clip(v, m.space[k]) for k, v in m.defaults.items() if k in m.space})
            first.append((m, m.study.ask(m.space)))
        (first if any(t.number == 0 for _, t in targets) else rest).extend(targets)
    _run_wave(first, NoPruning(), executor, out, echo)
    for m in plans:
        asked = len([t for t in m.study.get_trials(deepcopy=False) if t.state != optuna.trial.TrialState.WAITING])
        rest += [(m, m.study.ask(m.space)) for _ in range(max(0, trials - asked))]
    _run_wave(sorted(rest, key=lambda p: (p[1].number, p[0].name)), pruning, executor, out, echo)


def _clip(value: float, distribution) -> float:
    return min(max(float(value), distribution.low), distribution.high)


def _run_wave(pairs, pruning, executor: AbstractExecutor, out: Path, echo) -> None:
    """Run trials rung by rung (one rung without pruning) and tell Optuna their results."""
    import optuna

    alive = list(pairs)
    for m in {m.name: m for m, _ in alive}.values():
        if m.steps is None and not isinstance(pruning, NoPruning):
            raise ConfigError(f"{m.name}: pruning needs a steps or calibrated seconds budget")
    rungs = {m.name: pruning.rungs(m.steps) if m.steps is not None else [None] for m, _ in alive}
    for r in range(max((len(v) for v in rungs.values()), default=0)):
        jobs, scores = [], {}
        for m, trial in alive:
            steps = rungs[m.name][min(r, len(rungs[m.name]) - 1)]
            run_dir = trial_dir(out, m.name, trial.number)
            known = _score_at(run_dir, steps) if r < len(rungs[m.name]) - 1 else None
            if known is not None:
                scores[(m.name, trial.number)] = (known, None)
            else:
                jobs.append(((m, trial), m.make(trial.params, steps, run_dir)))
        for i, summary, error in executor.run([job for _, job in jobs]):
            m, trial = jobs[i][0]
            if error is not None:
                echo(f"{m.name} trial {trial.number}: failed ({type(error).__name__}: {error})")
                scores[(m.name, trial.number)] = (math.inf, None)
                trial.set_user_attr("error", f"{type(error).__name__}: {error}"[:500])
                m.study.tell(trial, state=optuna.trial.TrialState.FAIL)
                continue
            scores[(m.name, trial.number)] = (_score(summary), summary)
        survivors = []
        for name in dict.fromkeys(m.name for m, _ in alive):
            # a failed job was told FAIL already
            group = [(m, t) for m, t in alive if m.name == name and _state(m, t) == optuna.trial.TrialState.RUNNING]
            last = r >= len(rungs[name]) - 1
            ranked = sorted(group, key=lambda p: (scores[(name, p[1].number)][0], p[1].number))
            keep = ranked if last else ranked[: max(1, math.ceil(len(ranked) / getattr(pruning, "eta", 1)))]
            for m, trial in ranked:
                value, summary = scores[(name, trial.number)]
                steps = rungs[name][min(r, len(rungs[name]) - 1)]
                if steps is not None:
                    trial.report(value if math.isfinite(value) else 1e300, steps)
                if last or (m, trial) not in keep:
                    _tell(m, trial, value, summary, pruned=not last, echo=echo)
                else:
                    survivors.append((m, trial))
        alive = survivors
        if not alive:
            break


def _state(m: _Method, trial) -> Any:
    return m.study._storage.get_trial(trial._trial_id).state


def _tell(m: _Method, trial, value: float, summary, *, pruned: bool, echo) -> None:
    import optuna

    params = ", ".join(f"{k}={v:.3g}" for k, v in trial.params.items())
    if pruned:
        m.study.tell(trial, state=optuna.trial.TrialState.PRUNED)
        echo(f"{m.name} trial {trial.number} ({params}): pruned at validation loss {value:.3e}")
    elif math.isfinite(value):
        m.study.tell(trial, value)
        echo(f"{m.name} trial {trial.number} ({params}): validation loss {value:.3e}")
    else:
        m.study.tell(trial, state=optuna.trial.TrialState.FAIL)
        echo(f"{m.name} trial {trial.number} ({params}): diverged or failed")


def _score(summary: dict[str, Any] | None) -> float:
    """A trial's validation loss: its final loss on the validation data (its run's test
    split); +∞ for a diverged or failed run."""
    if not summary or summary.get("status") != "finished" or summary.get("final_test_loss") is None:
        return math.inf
    value = float(summary["final_test_loss"])
    return value if math.isfinite(value) else math.inf


def _score_at(run_dir: str, steps: int | None) -> float | None:
    """The validation loss a run logged at ``steps`` (a finished rung), or None."""
    from .train import read_metrics

    path = Path(run_dir) / "metrics.csv"
    if steps is None or not path.exists():
        return None
    values = [float(r["value"]) for r in read_metrics(path)
              if r["split"] == "test" and r["metric"] == "loss" and int(r["step"]) == steps]  # fmt: skip
    return (values[-1] if math.isfinite(values[-1]) else math.inf) if values else None


def _best(m: _Method) -> dict[str, Any]:
    import optuna

    complete = [t for t in m.study.get_trials(deepcopy=False) if t.state == optuna.trial.TrialState.COMPLETE]
    if not complete:  # every trial diverged: the untuned configuration stands
        return {k: m.defaults[k] for k in m.space}
    best = min(complete, key=lambda t: (t.value, t.number))
    return dict(best.params)


def write_trials(out: Path, plans: list[_Method]) -> list[dict[str, Any]]:
    """``trials.csv``: one row per trial (method, number, state, validation loss, steps, run
    directory relative to ``out``, hyperparameters as JSON)."""
    from .study import write_csv

    rows = []
    for m in plans:
        for t in m.study.get_trials(deepcopy=False):
            if t.state.name == "WAITING":
                continue
            steps = max(t.intermediate_values) if t.intermediate_values else m.steps
            last = t.intermediate_values.get(steps) if t.intermediate_values else None
            value = t.value if t.value is not None else last
            run_dir = Path(trial_dir(out, m.name, t.number)).relative_to(out.resolve())
            rows.append({"method": m.name, "trial": t.number, "state": t.state.name, "val_loss": value,
                         "steps": steps, "run_dir": str(run_dir), "params": json.dumps(t.params, sort_keys=True)})  # fmt: skip
    write_csv(out / "trials.csv", TRIAL_COLUMNS, rows)
    return rows


# --- the chosen configurations on test ---------------------------------------------------------------
def _final(problem, plans, best, budget, seeds, out: Path, settings, executor, echo) -> list[dict[str, Any]]:
    """The chosen configuration of every method on seeds 0..seeds−1, on the full training
    split, evaluated on test: a compare study (registered problems) or the object's runs."""
    echo(f"the chosen configurations on {seeds} seeds, reported on test -> {out}")
    if isinstance(problem, str):
        from .study import compare

        chosen = {f"{m}.{k}": v for m, params in best.items() for k, v in params.items()}
        if isinstance(budget, Seconds):
            _carry_calibration(problem, [m.name for m in plans], budget, {**settings, **chosen}, out.parent, out)
        return compare(problem, [m.name for m in plans], range(seeds), budget, out, settings={**settings, **chosen},
                       echo=echo, record_failures=True, executor=executor)  # fmt: skip
    from .config import method_slug

    jobs, keys = [], []
    for m in plans:
        batch, train = object_settings(problem, m.name, settings)
        for s in range(seeds):
            run_dir = run_directory(out / "runs" / f"{method_slug(m.name)}-seed{s}")
            jobs.append(ObjectRun(problem, m.name, {**m.defaults, **best[m.name]}, batch, s, budget, run_dir, train))
            keys.append((m.name, s))
    rows = []
    for i, summary, error in executor.run(jobs):
        method, s = keys[i]
        if error is not None:
            echo(f"{method} seed {s}: failed ({type(error).__name__}: {error})")
            continue
        rows.append({"problem": problem.name, "method": method, "seed": s, **summary})
    return sorted(rows, key=lambda r: (r["method"], r["seed"]))


def _carry_calibration(problem: str, methods: list[str], budget: Budget, settings, tuned: Path, final: Path) -> None:
    """The trials' calibration recorded for the chosen configurations in ``final/`` (where it
    has none): the searched settings do not change a step's cost, so the test runs train the
    trials' steps (chosen at N steps, reported at N steps), not timed again under another load."""
    from .calibration import CALIBRATION_CSV, CALIBRATION_FILE, Calibration, csv_rows, fingerprint, read, write_csv
    from .study import plan

    old = read(tuned)
    if old is None or (final / CALIBRATION_FILE).exists():
        return
    record = dict(old.record)
    timed, chosen = dict(record.get("by_fingerprint") or {}), {}
    for config in plan(problem, methods, [0], budget, settings):
        entry = (record.get("methods") or {}).get(config.method) or {}
        if entry.get("stages"):  # a method the trials could not time is timed by the study
            timed[fingerprint(config)] = chosen[config.method] = entry
    record.update(by_fingerprint=timed, methods=chosen)
    final.mkdir(parents=True, exist_ok=True)
    rundir.atomic_write(final / CALIBRATION_FILE, json.dumps(record, indent=2, default=str) + "\n")
    write_csv(final / CALIBRATION_CSV, csv_rows(Calibration(record), list(chosen)))


__all__ = ["NoPruning", "SuccessiveHalving", "TuneResult", "default_sampler", "open_storage", "tune"]

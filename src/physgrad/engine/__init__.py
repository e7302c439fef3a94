"""The training engine: one run of methods on a problem, with objects in and a run directory out.

    physgrad.fit(problem, method, budget=Budget(steps=2000), out="runs/mine", seed=0)

``problem`` is any :class:`physgrad.problems.AbstractProblem` instance (the user's own
too: no registry), ``method`` an engine method (:class:`physgrad.methods.Method`: a rule and
an optax transformation) or a sequence of :class:`Phase` (e.g. Adam for 1,413 steps, then
HIG from those parameters). One run::

    data    = split(problem.make_data(fold_in(key(seed), 0)))   # split: TestSplit() or HoldOut(f)
    network = problem.initial_network(fold_in(key(seed), 1), data)
    loop:  state = step(state, batch)                      # one jitted function per step
           every epoch / eval_every steps / eval_seconds: full train and test metrics

The package, in the order of a run:

- :mod:`~physgrad.engine.types`: what the caller gives (:class:`Budget`, :class:`Phase`,
  :class:`TrainSettings`), what a run builds (:class:`Stage`, :class:`Setup`) and carries
  (:class:`TrainState`, what a checkpoint holds);
- :mod:`~physgrad.engine.splits`: which data a run trains on and evaluates as test
  (:class:`TestSplit`, the problem's own; :class:`HoldOut`, validation data for tuning);
- :mod:`~physgrad.engine.setup`: data, network, objective and stages
  (:func:`build_setup`), the same from shapes alone (:func:`abstract_setup`, shared with
  the bench) and the memory guard's :func:`preflight`;
- :mod:`~physgrad.engine.step`: the jitted step and evaluation, and :class:`Steps` (data
  on the devices, batch order, each stage's compiled step);
- :mod:`~physgrad.engine.strategies`: :class:`StopRule`, :class:`EvalSchedule`,
  :class:`Placement` and :class:`Fidelity` (PRDP);
- :mod:`~physgrad.engine.recording`: :class:`Recorder` (``metrics.csv``),
  :class:`Checkpointer`, the final files and reading run directories back;
  :mod:`~physgrad.engine.packed`: run-directory files kept gzipped, read whichever form
  they have;
- :mod:`~physgrad.engine.record`: the run's record (``config.json``) and when a recorded
  run is the same run; :mod:`~physgrad.engine.hyperparams`: the optimizer's
  hyperparameters in it;
- :mod:`~physgrad.engine.resume`: what a run directory already holds, read before a run
  builds anything (the same run?, its budget met?, a finished run's missing files,
  ``env.json`` kept across resumes);
- :mod:`~physgrad.engine.callbacks`: :class:`Callback` (``on_eval``, ``on_checkpoint``);
- :mod:`~physgrad.engine.result`: :class:`FitResult`, what :func:`fit` returns (summary,
  history, final network and state);
- :mod:`~physgrad.engine.run`: :func:`fit` and the loop, which takes the strategies as one
  bundle (:class:`~physgrad.engine.run.Strategies`).

Errors are :class:`physgrad.ConfigError` lines in the library's words (``resume=True``,
``out``, ``devices=``); the command line prints them with its flags
(:mod:`physgrad.harness.words`).
"""

from .callbacks import Callback
from .cpu_clock import run_cpu_time
from .record import identity as _identity  # noqa: F401 — resume identity (tests compare records with it)
from .recording import (
    ENV_PACKAGES,
    FINAL_STATUSES,
    METRICS_HEADER,
    Checkpointer,
    MetricsLog,
    Recorder,
    environment,
    finish,
    is_complete,
    read_metrics,
    read_summary,
    write_json,
)
from .result import FitResult, history_from_metrics
from .run import Strategies, fit, loop
from .setup import (
    NOT_TRACEABLE,
    AbstractSetup,
    abstract_data,
    abstract_setup,
    build_setup,
    build_stages,
    initial_network,
    preflight,
    scalar_loss,
)
from .splits import AbstractSplit, HoldOut, TestSplit
from .step import Steps, grouped_order, make_evaluate, make_step
from .strategies import EvalSchedule, Fidelity, Placement, StopRule
from .types import (
    ADDED_SETTINGS,
    UNGUARDED_SETTINGS,
    Budget,
    Ending,
    Phase,
    Setup,
    Stage,
    TrainSettings,
    TrainState,
)

__all__ = [
    "ADDED_SETTINGS", "ENV_PACKAGES", "FINAL_STATUSES", "METRICS_HEADER", "NOT_TRACEABLE", "UNGUARDED_SETTINGS",
    "AbstractSetup", "AbstractSplit", "Budget", "Callback", "Checkpointer", "Ending", "EvalSchedule", "Fidelity", "FitResult",
    "HoldOut", "MetricsLog", "Phase", "Placement", "Recorder", "Setup", "Stage", "Steps", "StopRule", "Strategies",
    "TestSplit", "TrainSettings", "TrainState", "abstract_data", "abstract_setup", "build_setup", "build_stages", "environment",
    "finish", "fit", "grouped_order", "history_from_metrics", "initial_network", "is_complete", "loop",
    "make_evaluate", "make_step", "preflight", "read_metrics", "read_summary", "run_cpu_time", "scalar_loss",
    "write_json",
]  # fmt: skip

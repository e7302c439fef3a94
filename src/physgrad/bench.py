"""Benchmark every applicable method on every chosen problem at equal budgets, ranked.

    physgrad bench                                   # every shipped problem, every applicable method
    physgrad bench --quick                           # a handful of fast problems, ~10 s per run, 2 seeds
    physgrad bench --seconds 600 --seeds 5           # the long version (hours to days on a few cores)
    physgrad bench --problems oscillators,sine --methods adam,hig,optax:lion --steps 500

A bench directory (default ``bench/``) holds one study directory per problem,
``BENCH/<problem>/``, laid out exactly as ``physgrad compare`` writes it (``study.json``,
``runs/``, ``summary.csv``, ``results.csv``, ``paired_tests.csv``, ``loss_vs_time.png``),
so ``physgrad report BENCH/<problem>`` works on it, and running the same bench again skips
finished (or diverged) runs and resumes interrupted ones from their checkpoints. Next to
them:

- ``BENCH/<problem>/bench_table.csv`` / ``.md``: per method the final test loss (mean ± std
  over the finished seeds), its rank, its ratio to Adam's mean and the paired test against
  the problem's best method;
- ``BENCH/leaderboard.csv`` / ``.md``: per method the geometric-mean ratio to Adam over
  the problems it ran on, its wins (rank 1), divergences and failures;
- ``BENCH/heatmap.png``: log₁₀(ratio to Adam), method × problem;
- ``BENCH/bench.md``: all of it, with the budgets, settings and machine;
- ``BENCH/bench.json``: what was asked and the applicability of every candidate.

**Applicability.** A candidate method is applicable to a problem when the run's
configuration resolves and the method's own ``check`` accepts the problem's
:class:`~physgrad.methods.Objective` (and its batch size fits the training set): the
Jacobian methods need ``predict``/``loss`` and a differentiable simulator, SIP the
network/simulate split and a target, the BPTT variants a rollout (closed-loop problems),
ONE/NOG/WIG an unrolled time-stepper. It is decided from shapes alone
(``equinox.filter_eval_shape``), without generating data or training. On top of that
:data:`POLICY` skips a few pairings that make no sense as a bench entry (``newton``'s dense
Hessian on networks of more than :data:`NEWTON_MAX_PARAMS` parameters); they are listed
with the reason.

**Failures.** A run that the engine refuses (the memory guard) or that raises is recorded in
``BENCH/<problem>/failures.json`` and the bench goes on; a diverged run is an ordinary
finished study run with status ``diverged``. Refused runs are tried again on the next
invocation (a refusal costs seconds; the cause may have been fixed).

**The metric** is the one ``compare``'s table uses: each run's final test loss
(``summary.csv``). A method ranks by the fraction of its seeds that diverged first (a method
that diverges is less useful than any that does not), then by its mean final test loss
over the finished seeds. The paired test is ``physgrad.stats``' two-sided Wilcoxon
signed-rank test on (seed, test case) pairs of the per-case final test loss, finished
seeds only.

Everything here is a pure function of its arguments and the files it reads; nothing
changes global state on import.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .config import (  # isort: skip
    Budget, ConfigError, RunConfig, choose, make_config, parse_method, phase_methods, split_methods, valid_settings,
)  # fmt: skip
from .extras import MissingExtra
from .registry import METHODS, PROBLEMS

REFERENCE = "adam"  # the ratio column and the heat map are relative to this method

# Ratios enter logarithms (heat map, geometric mean) clipped to this range: a method that
# reaches a loss of exactly 0 (toy2d's Newton and SIP) has ratio 0, whose log would make
# every mean it enters -inf, and one blow-up should not outweigh many problems either.
RATIO_CLIP = (1e-6, 1e6)

# newton builds the dense Hessian of the batch loss: dim θ² memory and dim θ Hessian-vector
# products per step. Meant for direct optimisation of a few variables (methods/newton.py);
# on a network of tens of thousands of weights one step takes minutes and the memory guard
# cannot tell (Newton declares no footprint), so a bench would spend its budget compiling.
NEWTON_MAX_PARAMS = 5000

# The quick profile (``physgrad bench --quick``): the fastest open-loop problems, measured on
# 2 CPU cores (setup and compilation of every method in seconds), 10 s of training per run
# and 2 seeds. Measured on 2 cores shared with other jobs (load ~6): a 10 s run costs ~18 s
# of wall-clock (setup, compilation, evaluation); the first version's 118 runs took 36
# minutes, so the curated list below (142 runs) takes about 43. The two problems with 65,536 training samples get
# 4,096 (an epoch, and so a full evaluation, every ~40 steps instead of ~650); the Jacobian
# methods on the oscillators take the demo's batch of 32 instead of the paper's 128 (at 128 a
# step costs ~5 s on 2 cores: two steps in a 10 s run). Evaluation every 2 training seconds
# gives every curve a few points.
# The optax optimizers a default bench adds to the registered methods: Adam with decoupled
# weight decay, and two newer first-order methods (sign momentum; orthogonalised momentum).
ZOO = ("optax:adamw", "optax:lion", "optax.contrib:muon")

QUICK: dict[str, Any] = {
    "problems": ("hig_toy", "toy2d", "exp_inverse", "sine", "linear_oscillators", "oscillators"),
    # The candidates of the quick profile: the DP baselines that did best in the HIG paper's
    # comparison (Adam, RMSprop, SGD; Adagrad and Adadelta trail them) plus every
    # curvature and inversion method and the zoo (the rollout methods apply to none of them).
    "methods": ("adam", "sgd", "rmsprop", "gn", "hig", "lm", "kfac", "sip", "newton", *ZOO),
    "settings": {
        "exp_inverse.n_train": "4096", "sine.n_train": "4096", "eval_seconds": "2",
        "oscillators.gn.batch_size": "32", "oscillators.hig.batch_size": "32", "oscillators.lm.batch_size": "32",
    },
    "seconds": 10.0,
    "seeds": 2,
}  # fmt: skip


def quick_settings(problems: Sequence[str], methods: Sequence[str]) -> dict[str, Any]:
    """The quick profile's settings that concern ``problems`` and the candidate ``methods``
    (those scoped to another problem or to a method not among the candidates dropped)."""
    stages = {m for spec in methods for m in phase_methods(spec)}
    keep = {}
    for key, value in QUICK["settings"].items():
        head, _, rest = key.partition(".")
        if head in PROBLEMS and rest:
            if head not in problems:
                continue
            key = rest
        target = key.rpartition(".")[0]
        if not target or target in stages:
            keep[f"{head}.{key}" if head in PROBLEMS and rest else key] = value
    return keep


# --- names and settings ------------------------------------------------------------------


def choose_problems(text: str | None) -> list[str]:
    """``None``/``"all"`` → every shipped problem; else the comma-separated names, checked
    (a one-line :class:`ConfigError` with the valid choices)."""
    if text is None or text.strip() == "all":
        return list(PROBLEMS)
    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise ConfigError(f"--problems is empty; valid choices: all, {', '.join(sorted(PROBLEMS))}")
    for name in names:
        choose("problem", name, PROBLEMS)
    return list(dict.fromkeys(names))


def choose_methods(text: str | None) -> list[str]:
    """``None``/``"applicable"`` → every registered method and the optax optimizers of
    :data:`ZOO` (each problem keeps those that apply); else the listed specs, each checked by ``config.parse_method`` (which owns the
    method names, colon names such as ``optax:lion`` included)."""
    if text is None or text.strip() == "applicable":
        return [*METHODS, *ZOO]
    specs = split_methods(text)
    if not specs:
        raise ConfigError(f"--methods is empty; valid choices: applicable, {', '.join(sorted(METHODS))}")
    for spec in specs:
        parse_method(spec)
    return list(dict.fromkeys(specs))


def problem_settings(problem: str, method: str, settings: dict[str, Any]) -> dict[str, Any]:
    """The subset of a bench's ``--set`` values for one (problem, method) run.

    ``name=value`` applies where the setting exists (a problem setting, a method
    hyperparameter or a training setting); ``m.name=value`` to method ``m`` (or the stage
    ``m`` of a sequence); ``p.name=value`` with ``p`` a problem to that problem only (and
    ``p.m.name`` to method ``m`` on problem ``p``). Names that exist nowhere are refused by
    :func:`check_settings` before anything runs."""
    names = set(phase_methods(method))
    valid = valid_settings(problem, method)
    out = {}
    for key, value in settings.items():
        head, _, rest = key.partition(".")
        if head in PROBLEMS and rest:
            if head != problem:
                continue
            key = rest
        target, _, name = key.rpartition(".")
        if target:
            if target in names and name in valid:
                out[key] = value
        elif name in valid:
            out[name] = value
    return out


def check_settings(problems: Sequence[str], methods: Sequence[str], settings: dict[str, Any]) -> None:
    """Refuse (one line) a setting that no chosen problem/method pairing has, or a scope
    that names no chosen problem or method."""
    everywhere: set[str] = set()
    for problem in problems:
        for method in methods:
            everywhere |= set(valid_settings(problem, method))
    stages = sorted({m for spec in methods for m in phase_methods(spec)})
    for key in settings:
        head, _, rest = key.partition(".")
        if head in PROBLEMS and rest:
            choose("problem in a scoped setting", head, problems)
            key = rest
        target, _, name = key.rpartition(".")
        if target:
            choose("method in a scoped setting", target, stages)
        if name not in everywhere:
            raise ConfigError(f"unknown setting {name!r}; valid choices: {', '.join(sorted(everywhere))}")


# --- applicability ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Verdict:
    """Whether a method runs on a problem in the bench: ``status`` is ``"applicable"``,
    ``"not applicable"`` (the method's check refused the problem), ``"skipped"`` (by
    :data:`POLICY`) or ``"error"`` (the check itself failed: recorded as a failure)."""

    method: str
    status: str
    reason: str = ""

    @property
    def runs(self) -> bool:
        return self.status == "applicable"


def _newton_policy(method: str, n_params: int) -> str:
    if "newton" in phase_methods(method) and n_params > NEWTON_MAX_PARAMS:
        return (f"newton's dense Hessian of {n_params} network parameters (> {NEWTON_MAX_PARAMS}): "
                "minutes per step; newton is for direct optimisation (--set no_network=true)")  # fmt: skip
    return ""


# Bench-only exclusions: (method spec, trainable parameter count) -> reason, or "" to keep.
POLICY: tuple[Callable[[str, int], str], ...] = (_newton_policy,)


def applicability(problem: str, methods: Sequence[str], settings: dict[str, Any] | None = None) -> list[Verdict]:
    """Decide for each method spec whether it runs on ``problem`` under the bench's
    ``settings`` (see the module docstring), without generating data or training.

    Raises :class:`ConfigError` for a bad setting value (the user's input, not the
    method's fault)."""
    from .engine import abstract_setup
    from .precision import float64_scope
    from .train import phases_of, problem_of

    settings = settings or {}
    objectives: dict[str, tuple] = {}  # the objective depends on the problem's settings only
    verdicts = []
    for method in methods:
        try:
            config = make_config(
                problem, method, budget=Budget(steps=1), settings=problem_settings(problem, method, settings)
            )
        except MissingExtra as e:  # an optional extra is not installed: listed with the pip line
            verdicts.append(Verdict(method, "skipped", _one_line(e)))
            continue
        phases = phases_of(config)
        problem_obj = problem_of(config)
        cache_key = json.dumps([config.problem_settings, config.no_network], sort_keys=True, default=str)
        try:
            with float64_scope(problem_obj.needs_float64):
                if cache_key not in objectives:
                    shapes = abstract_setup(problem_obj)  # the engine's, as its memory preflight sees it
                    objectives[cache_key] = (
                        shapes.n_train,
                        shapes.parameter_count,
                        problem_obj.objective(shapes.static),
                    )
                n_train, size, objective = objectives[cache_key]
                for phase in phases:
                    batch_size = phase.batch_size
                    assert batch_size is not None  # the config's, resolved
                    phase.method.check(objective)
                    phase.method.check_batch_size(batch_size)
                    if n_train is not None and batch_size > n_train:
                        raise ValueError(f"batch_size {batch_size} exceeds the {n_train} training samples")
        # the contract of check(): one line saying what to use instead; ConfigError (a ValueError)
        # e.g. for SIP's solver resolution on a problem without an inverse
        except ValueError as e:
            verdicts.append(Verdict(method, "not applicable", _one_line(e)))
            continue
        except Exception as e:  # noqa: BLE001 — a check that crashed: a failure to report, not a crash
            verdicts.append(Verdict(method, "error", f"{type(e).__name__}: {_one_line(e)}"))
            continue
        reason = next((r for r in (rule(method, size) for rule in POLICY) if r), "")
        verdicts.append(Verdict(method, "skipped", reason) if reason else Verdict(method, "applicable"))
    return verdicts


def _one_line(e: BaseException) -> str:
    text = str(e).strip() or type(e).__name__
    return " ".join(text.split())


# --- running ---------------------------------------------------------------------------------


def scoped_settings(problem: str, settings: dict[str, Any]) -> dict[str, Any]:
    """The bench's ``--set`` values as ``problem`` sees them: its own ``problem.name`` keys
    unscoped, other problems' keys dropped (what its ``study.json`` records)."""
    out = {}
    for key, value in settings.items():
        head, _, rest = key.partition(".")
        if head in PROBLEMS and rest:
            if head == problem:
                out[rest] = value
        else:
            out[key] = value
    return out


def plan_problem(
    problem: str, verdicts: Sequence[Verdict], seeds: Sequence[int], budget: Budget, settings: dict[str, Any]
) -> list[RunConfig]:
    """The run configurations of one problem's study: every applicable method × seed."""
    return [
        make_config(problem, v.method, budget=budget, seed=s, settings=problem_settings(problem, v.method, settings))
        for v in verdicts
        if v.runs
        for s in seeds
    ]


def read_failures(out: str | Path) -> dict[str, dict[str, Any]]:
    """``failures.json`` of a problem's study: {run name: {method, seed, error}}."""
    path = Path(out) / "failures.json"
    return json.loads(path.read_text()) if path.exists() else {}


def _write_json(path: Path, data: Any) -> None:
    from .rundir import atomic_write

    atomic_write(path, json.dumps(data, indent=2, default=str) + "\n")  # an interrupted bench never leaves half a file


def run_problem(
    problem: str,
    verdicts: Sequence[Verdict],
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    progress: Callable[[], Any] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
) -> list[dict[str, Any]]:
    """One problem's study in ``out``, as :func:`physgrad.study.compare` runs it (the same
    ``study.json``, run directories, skipping and resuming), except that a run which raises
    (the memory guard's refusal, a crash) is recorded in ``failures.json`` and the others go
    on; ``compare`` stops at the first error, which a bench of every method cannot afford.
    Returns the study's summary rows (:func:`physgrad.study.collect`)."""
    from .rundir import one_writer
    from .study import collect, describe_run, run_name
    from .train import is_complete, read_summary, train

    out = Path(out)
    settings = settings or {}
    configs = plan_problem(problem, verdicts, seeds, budget, settings)
    with one_writer(out, "study"):  # one writer per study directory (as compare)
        names = [run_name(c) for c in configs]
        _write_json(out / "study.json", {
            "problem": problem, "methods": list(dict.fromkeys(c.method for c in configs)), "seeds": list(seeds),
            "budget": budget.to_dict(), "settings": scoped_settings(problem, settings), "runs": names,
        })  # fmt: skip
        failures = {k: v for k, v in read_failures(out).items() if k in names}  # the current plan's only
        for i, (config, name) in enumerate(zip(configs, names), 1):
            run_dir = out / "runs" / name
            prefix = f"{problem} [{i}/{len(configs)}] {config.method} seed {config.seed}"
            if is_complete(run_dir):
                echo(f"{prefix}: done already ({(read_summary(run_dir) or {}).get('status')}), skipped")
                continue
            try:
                summary = train(
                    config, run_dir, resume=True, progress=progress() if progress else None, devices=devices
                )
            except Exception as e:  # noqa: BLE001 — KeyboardInterrupt is not an Exception: it still stops the bench
                failures[name] = {
                    "method": config.method,
                    "seed": config.seed,
                    "error": f"{type(e).__name__}: {_one_line(e)}",
                }
                _write_json(out / "failures.json", failures)
                echo(f"{prefix}: failed, recorded ({failures[name]['error']})")
                continue
            failures.pop(name, None)
            _write_json(out / "failures.json", failures)
            echo(f"{prefix}: {describe_run(summary)}")
        _write_json(out / "failures.json", failures)
        return collect(out)


# --- tables: pure functions of summary rows ------------------------------------------------------


def _float(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def method_rows(
    rows: Sequence[dict[str, Any]],
    verdicts: Sequence[Verdict],
    failures: dict[str, dict[str, Any]] | None = None,
    reference: str = REFERENCE,
) -> list[dict[str, Any]]:
    """Per candidate method of one problem: status, counts, mean ± std of the final test
    loss over its finished seeds, rank and ratio to ``reference``.

    ``rows``: the study's ``summary.csv`` rows (``method``, ``status``, ``final_test_loss``);
    ``failures``: ``failures.json``. ``status`` is ``ok`` (a finished seed),
    ``diverged`` (every run diverged), ``failed`` (every run failed or the check crashed),
    ``not applicable``, ``skipped`` or ``pending`` (applicable, not run yet).
    The rank orders the methods with a mean by (fraction of runs diverged or failed, mean);
    equal keys share the lower rank. The ratio is mean / reference mean where both are
    finite and the reference's is positive."""
    failures = failures or {}
    table = []
    for v in verdicts:
        runs = [r for r in rows if r["method"] == v.method]
        finished = [r for r in runs if r["status"] == "finished"]
        diverged = sum(r["status"] == "diverged" for r in runs)
        failed = sum(f["method"] == v.method for f in failures.values()) + (v.status == "error")
        values = np.array([_float(r["final_test_loss"]) for r in finished], dtype=float)
        values = values[np.isfinite(values)]
        mean = float(values.mean()) if values.size else math.nan
        std = float(values.std(ddof=1)) if values.size > 1 else (0.0 if values.size else math.nan)
        if v.status != "applicable" and v.status != "error":
            status = v.status
        elif values.size:
            status = "ok"
        elif diverged:
            status = "diverged"
        elif failed:
            status = "failed"
        else:
            status = "pending"
        table.append({
            "method": v.method, "status": status, "reason": v.reason, "runs": len(runs) + failed,
            "finished": int(values.size), "diverged": diverged, "failed": failed, "mean": mean, "std": std,
        })  # fmt: skip
    ranked = sorted(
        (t for t in table if math.isfinite(t["mean"])),
        key=lambda t: ((t["diverged"] + t["failed"]) / max(t["runs"], 1), t["mean"]),
    )
    rank, previous = 0, None
    for i, t in enumerate(ranked, 1):
        key = ((t["diverged"] + t["failed"]) / max(t["runs"], 1), t["mean"])
        rank = rank if key == previous else i
        t["rank"], previous = rank, key
    base = next((t["mean"] for t in table if t["method"] == reference), math.nan)
    for t in table:
        t.setdefault("rank", None)
        t["problem_has_reference"] = math.isfinite(base) and base > 0
        t["ratio"] = t["mean"] / base if math.isfinite(t["mean"]) and t["problem_has_reference"] else math.nan
    return table


def best_method(table: Sequence[dict[str, Any]]) -> str | None:
    """The rank-1 method (the first of a tie), or None if no method has a result."""
    return next((t["method"] for t in sorted(table, key=lambda t: t["rank"] or math.inf) if t["rank"] == 1), None)


def add_paired_tests(table: list[dict[str, Any]], tests: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each method's paired test against the best method (``stats.paired_tests`` rows):
    ``p_vs_best`` (two-sided Wilcoxon signed-rank p-value), ``pairs``, ``seeds_best_lower``
    (of ``seeds_compared``); NaN/None where there is nothing to pair."""
    best = best_method(table)
    for t in table:
        row = next((r for r in tests if best and {r["method_a"], r["method_b"]} == {best, t["method"]}), None)
        t["best"] = best
        if row is None or t["method"] == best:
            t.update(p_vs_best=math.nan, pairs=0, seeds_best_lower=None, seeds_compared=None)
            continue
        best_first = row["method_a"] == best
        seeds, lower = int(row["seeds"]), int(row["seeds_a_lower"])
        t.update(p_vs_best=_float(row["p_value"]), pairs=int(row["pairs"]), seeds_compared=seeds,
                 seeds_best_lower=lower if best_first else seeds - lower)  # fmt: skip
    return table


def leaderboard(tables: dict[str, Sequence[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per method over the problems (``{problem: method_rows(...)}``): the geometric mean of
    its ratios to the reference (over the problems where the ratio is defined; each ratio
    clipped to :data:`RATIO_CLIP`), the number
    of problems that ratio covers, wins (rank 1, ties included), diverged and failed runs,
    and the problems it ran on (applicable, not skipped).

    Sorted by ``score``: the same geometric mean, but over every problem it ran on where
    the reference has a result, a problem where every run of the method diverged or failed
    counting as the worst ratio, ``RATIO_CLIP[1]`` (otherwise a method that diverges on most
    problems would lead on the one or two where it converged); then by wins."""
    methods = list(dict.fromkeys(t["method"] for table in tables.values() for t in table))
    board = []
    for method in methods:
        cells = [t for table in tables.values() for t in table if t["method"] == method]
        ran = [t for t in cells if t["status"] not in ("not applicable", "skipped")]
        if not ran:
            continue
        ratios = np.clip([t["ratio"] for t in ran if math.isfinite(t["ratio"])], *RATIO_CLIP)
        lost = sum(t["status"] in ("diverged", "failed") for t in ran if t["problem_has_reference"])
        scored = np.concatenate([ratios, np.full(lost, RATIO_CLIP[1])])
        board.append({
            "method": method,
            "score": float(10 ** np.mean(np.log10(scored))) if scored.size else math.nan,
            "geomean_ratio": float(10 ** np.mean(np.log10(ratios))) if ratios.size else math.nan,
            "ratio_problems": int(ratios.size),
            "wins": sum(t["rank"] == 1 for t in ran),
            "divergences": sum(t["diverged"] for t in ran),
            "failures": sum(t["failed"] for t in ran),
            "problems": len(ran),
            "runs": sum(t["runs"] for t in ran),
        })  # fmt: skip

    def key(b):
        finite = math.isfinite(b["score"])
        return (not finite, b["score"] if finite else 0, -b["wins"])

    board.sort(key=key)
    return board


# --- formatting ------------------------------------------------------------------------------

TABLE_COLUMNS = (
    "problem", "method", "status", "runs", "finished", "diverged", "failed", "final_test_loss_mean",
    "final_test_loss_std", "rank", "ratio_to_adam", "best", "p_vs_best", "pairs", "seeds_best_lower",
    "seeds_compared", "reason",
)  # fmt: skip
BOARD_COLUMNS = (
    "method",
    "score",
    "geomean_ratio_to_adam",
    "ratio_problems",
    "wins",
    "divergences",
    "failures",
    "runs",
    "problems",
)


def _number(x: float, spec: str = ".3e") -> str:
    return format(x, spec) if isinstance(x, (int, float)) and math.isfinite(x) else ""


def table_records(problem: str, table: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """``method_rows`` (with paired tests) as ``bench_table.csv`` rows."""
    return [{
        "problem": problem, "method": t["method"], "status": t["status"], "runs": t["runs"],
        "finished": t["finished"], "diverged": t["diverged"], "failed": t["failed"],
        "final_test_loss_mean": _number(t["mean"], ".6e"), "final_test_loss_std": _number(t["std"], ".6e"),
        "rank": t["rank"] or "", "ratio_to_adam": _number(t["ratio"], ".6g"), "best": t.get("best") or "",
        "p_vs_best": _number(t.get("p_vs_best", math.nan), ".3g"), "pairs": t.get("pairs") or "",
        "seeds_best_lower": "" if t.get("seeds_best_lower") is None else t["seeds_best_lower"],
        "seeds_compared": t.get("seeds_compared") or "", "reason": t["reason"],
    } for t in table]  # fmt: skip


def table_lines(
    table: Sequence[dict[str, Any]], reference: str = REFERENCE, inapplicable: bool = True
) -> list[list[str]]:
    """A problem's table as printable lines (header first): ranked methods first, then the
    diverged/failed/pending ones, then (with ``inapplicable``) the skipped methods and
    those that do not apply, with the reason."""
    from .stats import format_p

    best = best_method(table)
    header = ["rank", "method", "runs", "final test loss (mean ± std)", f"/ {reference}",
              f"vs {best or 'best'}: Wilcoxon p (seeds lower)", "note"]  # fmt: skip
    order = {"ok": 0, "diverged": 1, "failed": 1, "pending": 2, "skipped": 3, "not applicable": 4}
    lines = [header]
    for t in sorted(table, key=lambda t: (order[t["status"]], t["rank"] or 0)):
        if not inapplicable and t["status"] in ("skipped", "not applicable"):
            continue
        notes = []
        if t["diverged"]:
            notes.append(f"{t['diverged']}/{t['runs']} diverged")
        if t["failed"]:
            notes.append(f"{t['failed']}/{t['runs']} failed")
        if t["reason"]:
            notes.append(t["reason"])
        if t["status"] == "ok":
            loss = f"{t['mean']:.3e} ± {t['std']:.1e}"
        else:
            loss = {"diverged": "all diverged", "failed": "failed", "pending": "not run yet"}.get(
                t["status"], str(t["status"])
            )
        if t["method"] == best:
            test = "best"
        elif t.get("pairs"):
            test = f"{format_p(t['p_vs_best'])} ({t['seeds_best_lower']}/{t['seeds_compared']})"
        else:
            test = ""
        ratio = _number(t["ratio"], ".3g")
        runs = str(t["runs"]) if t["status"] not in ("not applicable", "skipped") else ""
        lines.append([str(t["rank"] or ""), t["method"], runs, loss, ratio, test, "; ".join(notes)])
    return lines


def board_records(board: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**{k: b[k] for k in BOARD_COLUMNS if k in b}, "score": _number(b["score"], ".6g"),
             "geomean_ratio_to_adam": _number(b["geomean_ratio"], ".6g")}
            for b in board]  # fmt: skip


def board_lines(board: Sequence[dict[str, Any]], reference: str = REFERENCE) -> list[list[str]]:
    header = ["method", f"score (all diverged = {RATIO_CLIP[1]:g})", f"geo-mean ratio to {reference}", "problems (ratio)",
              "wins", "diverged runs", "failed runs", "problems run"]  # fmt: skip
    lines = [header]
    for b in board:
        runs = b.get("runs") or 0
        lines.append([b["method"], _number(b["score"], ".3g") or "-", _number(b["geomean_ratio"], ".3g") or "-", str(b["ratio_problems"]), str(b["wins"]),
                      f"{b['divergences']}/{runs}", f"{b['failures']}/{runs}", str(b["problems"])])  # fmt: skip
    return lines


def _write_rows(path: Path, columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> None:
    """A table written all at once (:func:`physgrad.rundir.atomic_write`)."""
    import csv
    import io

    from .rundir import atomic_write

    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(columns), extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(path, text.getvalue())


def heatmap(
    tables: dict[str, Sequence[dict[str, Any]]], path: str | Path, *, title: str = "", reference: str = REFERENCE
) -> Path:
    """Method × problem heat map of log₁₀(mean final test loss / the reference's): blue
    below the reference, red above; the ratio is written in each cell (``†``: some seeds
    diverged or failed). Cells whose runs all diverged or failed are grey, hatched and
    crossed; methods that do not apply (or were skipped, or have not run) are blank; ``n/a``:
    ran, but the reference has no result to compare with."""
    from matplotlib.figure import Figure  # its own canvas: no pyplot, no backend switch
    from matplotlib.patches import Rectangle

    problems = list(tables)
    methods = list(dict.fromkeys(t["method"] for table in tables.values() for t in table
                                 if t["status"] not in ("not applicable", "skipped")))  # fmt: skip
    cell = {(p, t["method"]): t for p, table in tables.items() for t in table}
    values = np.full((len(methods), len(problems)), np.nan)
    for i, m in enumerate(methods):
        for j, p in enumerate(problems):
            t = cell.get((p, m))
            if t and math.isfinite(t["ratio"]):
                values[i, j] = math.log10(min(max(t["ratio"], RATIO_CLIP[0]), RATIO_CLIP[1]))
    finite = values[np.isfinite(values)]
    limit = min(max(1.0, float(np.abs(finite).max()) if finite.size else 1.0), 4.0)  # beyond ±4: saturated
    fig = Figure(figsize=(1.5 + 0.9 * max(len(problems), 1), 1.2 + 0.4 * max(len(methods), 1)), dpi=120)
    ax = fig.subplots()
    image = ax.imshow(np.ma.masked_invalid(values), cmap="RdBu_r", vmin=-limit, vmax=limit, aspect="auto")
    for i, m in enumerate(methods):
        for j, p in enumerate(problems):
            t = cell.get((p, m))
            if t is None or t["status"] in ("not applicable", "skipped", "pending"):
                continue
            if t["status"] in ("diverged", "failed"):
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, facecolor="0.85", hatch="xx", edgecolor="0.5", lw=0))
                ax.text(
                    j, i, "diverged" if t["status"] == "diverged" else "failed", ha="center", va="center", fontsize=6
                )
            elif np.isfinite(values[i, j]):
                mark = "†" if t["diverged"] or t["failed"] else ""
                ax.text(j, i, f"{t['ratio']:.2g}{mark}", ha="center", va="center", fontsize=6,
                        color="white" if abs(values[i, j]) > 0.6 * limit else "black")  # fmt: skip
            else:
                ax.text(j, i, "n/a", ha="center", va="center", fontsize=6, color="0.4")
    ax.set_xticks(range(len(problems)), problems, rotation=45, ha="right", fontsize=7)
    ax.set_yticks(range(len(methods)), methods, fontsize=7)
    ax.set_xlim(-0.5, len(problems) - 0.5)
    ax.set_ylim(len(methods) - 0.5, -0.5)
    bar = fig.colorbar(image, ax=ax, fraction=0.05, pad=0.02)
    bar.set_label(f"log10(final test loss / {reference}'s)", fontsize=7)
    bar.ax.tick_params(labelsize=6)
    ax.set_title(title or f"final test loss relative to {reference} (blue: lower; blank: not applicable)", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    return path


# --- the bench -------------------------------------------------------------------------------


def machine() -> dict[str, Any]:
    """What the budgets were spent on: CPU cores (all, and usable by this process), JAX's
    backend and devices, versions (``engine.environment``)."""
    from .engine import environment

    env = environment()
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        usable = os.cpu_count()
    import jax

    kinds = sorted({getattr(d, "device_kind", d.platform) for d in jax.devices()})
    return {**env, "usable_cpus": usable, "device_kind": ", ".join(kinds)}


def plan(
    problems: Sequence[str],
    methods: Sequence[str],
    settings: dict[str, Any] | None = None,
    echo: Callable[[str], None] = lambda line: None,
) -> dict[str, list[Verdict]]:
    """Every problem's verdicts on every candidate method, after checking the settings:
    all input errors surface here, before anything trains."""
    settings = settings or {}
    check_settings(problems, methods, settings)
    verdicts = {}
    for problem in problems:
        verdicts[problem] = applicability(problem, methods, settings)
        echo(f"{problem}: {describe_verdicts(verdicts[problem])}")
    return verdicts


def describe_verdicts(verdicts: Sequence[Verdict]) -> str:
    """One line: the applicable methods, then the others grouped by status."""
    parts = [f"runs {', '.join(v.method for v in verdicts if v.runs) or 'nothing'}"]
    for status in ("not applicable", "skipped", "error"):
        names = [v.method for v in verdicts if v.status == status]
        if names:
            parts.append(f"{status}: {', '.join(names)}")
    return "; ".join(parts)


class BenchReport(NamedTuple):
    """The bench's tables (``{problem: method rows}``), leaderboard and written files."""

    tables: dict[str, list[dict[str, Any]]]
    board: list[dict[str, Any]]
    files: dict[str, Path | None]  # the heat map's is None where it could not be drawn (a FigureWarning)

    @property
    def lines(self) -> list[list[str]]:
        """The leaderboard's printable lines."""
        return board_lines(self.board)


def bench(
    problems: Sequence[str],
    methods: Sequence[str],
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    progress: Callable[[], Any] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    profile: str = "",
) -> BenchReport:
    """Run the bench into ``out`` (see the module docstring) and write its report.

    ``methods`` are the candidates (each problem runs those that apply); ``settings`` the
    ``--set`` values (``p.name`` scopes to problem ``p``); ``profile`` names a preset such
    as ``quick`` in the report."""
    from .rundir import one_writer

    settings = settings or {}
    out = Path(out)
    verdicts = plan(problems, methods, settings, echo=echo)
    with one_writer(out, "bench"):  # one writer per bench directory, for the whole bench
        _write_json(out / "bench.json", {
            "problems": list(problems), "methods": list(methods), "seeds": list(seeds), "budget": budget.to_dict(),
            "settings": settings, "profile": profile, "devices": devices,
            "verdicts": {p: [dataclasses.asdict(v) for v in vs] for p, vs in verdicts.items()},
            "machine": machine(),
        })  # fmt: skip
        for i, problem in enumerate(problems, 1):
            runnable = sum(v.runs for v in verdicts[problem])
            echo(
                f"problem {i}/{len(problems)} {problem}: {runnable} methods x {len(seeds)} seeds, budget {budget} per run"
            )
            run_problem(problem, verdicts[problem], seeds, budget, out / problem, settings=settings, progress=progress,
                        echo=echo, devices=devices)  # fmt: skip
        return report(out)


def problem_table(out: str | Path, verdicts: Sequence[Verdict]) -> list[dict[str, Any]]:
    """One problem's method rows from its study directory, with the paired tests against
    the best method (written to its ``paired_tests.csv``: metric ``loss``, best first) and
    its loss-vs-time figure redrawn."""
    from .stats import paired_tests
    from .study import collect, read_csv
    from .study import report as study_report

    out = Path(out)
    rows = []
    if (out / "runs").exists():
        collect(out)  # the files may predate runs finished since (or a bench interrupted)
        rows = read_csv(out / "summary.csv")
    table = method_rows(rows, verdicts, read_failures(out))
    tests = []
    if rows:
        study_report(out)  # loss_vs_time.png, as compare draws it
        best = best_method(table)
        others = [t["method"] for t in table if t["method"] != best and t["finished"]]
        if best and others:
            tests = paired_tests(out, metric="loss", order=[best, *others])
    return add_paired_tests(table, tests)


def report(out: str | Path) -> BenchReport:
    """(Re)write a bench's tables, leaderboard, heat map and ``bench.md`` from its files
    (each written all at once)."""
    from .plots import draw
    from .rundir import atomic_write
    from .study import markdown

    out = Path(out)
    if not (out / "bench.json").exists():
        raise ConfigError(f"{out} is not a bench directory: bench.json is missing")
    info = json.loads((out / "bench.json").read_text())
    tables, files = {}, {}
    for problem in info["problems"]:
        verdicts = [Verdict(**v) for v in info["verdicts"][problem]]
        table = problem_table(out / problem, verdicts)
        tables[problem] = table
        (out / problem).mkdir(exist_ok=True)  # a bench interrupted before this problem: its table says pending
        _write_rows(out / problem / "bench_table.csv", TABLE_COLUMNS, table_records(problem, table))
        atomic_write(out / problem / "bench_table.md", markdown(table_lines(table)) + "\n")
    board = leaderboard(tables)
    _write_rows(out / "leaderboard.csv", BOARD_COLUMNS, board_records(board))
    atomic_write(out / "leaderboard.md", markdown(board_lines(board)) + "\n")
    _write_rows(out / "bench_table.csv", TABLE_COLUMNS, [r for p, t in tables.items() for r in table_records(p, t)])
    files["leaderboard"] = out / "leaderboard.csv"
    files["table"] = out / "bench_table.csv"
    files["markdown"] = out / "bench.md"
    atomic_write(out / "bench.md", bench_markdown(info, tables, board))
    files["heatmap"] = draw(  # last: a failing figure is a warning, the tables are written
        heatmap, tables, out / "heatmap.png", title=f"{_budget_text(info)}: final test loss relative to {REFERENCE}"
    )
    return BenchReport(tables, board, files)


def _budget_text(info: dict[str, Any]) -> str:
    budget = ", ".join(f"{v:g} {k}" for k, v in info["budget"].items())
    seeds = len(info["seeds"])
    return f"{budget} per run, {seeds} seed{'s' if seeds != 1 else ''}"


def bench_markdown(
    info: dict[str, Any], tables: dict[str, Sequence[dict[str, Any]]], board: Sequence[dict[str, Any]]
) -> str:
    """``bench.md``: budgets, machine, settings, leaderboard, heat map and every problem's table."""
    from .study import markdown

    m = info.get("machine", {})
    versions = m.get("versions", {})
    budget = info["budget"]
    kind = next(iter(budget))
    budget_line = {
        "seconds": f"{budget[kind]:g} s of training wall-clock per run (evaluation and compilation excluded), "
                   "the same for every method of a problem",
        "steps": f"{budget[kind]:g} training steps per run",
        "epochs": f"{budget[kind]:g} epochs per run",
    }[kind]  # fmt: skip
    settings = info.get("settings") or {}
    out = [
        "# physgrad bench" + (f" ({info['profile']} profile)" if info.get("profile") else ""),
        "",
        f"- **Budget**: {budget_line}; seeds {', '.join(map(str, info['seeds']))}.",
        f"- **Problems**: {', '.join(info['problems'])}.",
        f"- **Candidate methods**: {', '.join(info['methods'])} (each problem runs those that apply).",
        "- **Settings** (`--set`; `problem.name` applies to that problem only): "
        + (
            ", ".join(f"`{k}={v}`" for k, v in settings.items())
            if settings
            else "none (every problem and method at its paper defaults)"
        ),
        f"- **Machine**: {m.get('cpu_count')} CPU cores ({m.get('usable_cpus')} usable by the process), "
        f"backend {m.get('backend')} ({m.get('device_kind')}; {len(m.get('devices', []))} device(s)), "
        f"JAX {versions.get('jax')}, jaxlib {versions.get('jaxlib')}, physgrad {versions.get('physgrad')}, "
        f"Python {m.get('python')}, {m.get('platform')}; started {m.get('time')}.",
        "",
        "The metric is each run's final test loss (as in `physgrad compare`); per method its mean ± std over the "
        "finished seeds. Rank: by the fraction of runs that diverged or failed, then by that mean. "
        f"Ratio: mean / {REFERENCE}'s mean. The paired test against each problem's best method is the two-sided "
        "Wilcoxon signed-rank test on (seed, test case) pairs of the per-case final test loss, finished seeds of "
        'both methods only (`physgrad.stats`); "seeds lower" counts the seeds on which the best method\'s mean '
        "over test cases is lower.",
        "",
        "## Leaderboard",
        "",
        f"Geometric mean of the ratio to {REFERENCE} over the problems where both have a result (below 1: lower "
        "loss than Adam at the same budget); wins: problems where the method ranks first. Ordered by the score: "
        f"the same geometric mean, with a problem where every run of the method diverged or failed counting as a "
        f"ratio of {RATIO_CLIP[1]:g} (so a method cannot lead on the few problems where it converged).",
        "",
        markdown(board_lines(board)) if board else "(no runs yet)",
        "",
        "![method x problem heat map](heatmap.png)",
        "",
        "Heat map: log10 of the ratio to Adam (blue: lower loss); † some seeds diverged or failed; hatched: every "
        "run diverged or failed; blank: not applicable, skipped or not run; n/a: Adam has no result. Ratios enter "
        f"the logarithms clipped to [{RATIO_CLIP[0]:g}, {RATIO_CLIP[1]:g}] (a loss of exactly 0 has ratio 0).",
        "",
    ]
    for problem, table in tables.items():
        out += [f"## {problem}", "", markdown(table_lines(table)), ""]
        out += [f"Curves: [{problem}/loss_vs_time.png]({problem}/loss_vs_time.png); "
                f"files: `{problem}/summary.csv`, `{problem}/paired_tests.csv`, `{problem}/bench_table.csv`.", ""]  # fmt: skip
    out += [
        "## Longer budgets",
        "",
        "    physgrad bench --seconds 600 --seeds 5 --out bench-long",
        "",
        "runs every shipped problem with every applicable method for 10 minutes of training per run and 5 seeds "
        "(the same command again resumes it; `--problems a,b` and `--methods x,y` narrow it).",
        "",
    ]
    return "\n".join(out)

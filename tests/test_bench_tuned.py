"""physgrad bench --tuned (harness/bench/tuned.py, tuned_report.py): the integrated
performance profile against hand-computed numbers, a tuned bench from the command line with
its leaderboard recomputed from the kept files by a plain implementation written here, its
redraw and resume, bad input, and (slow) an interrupted bench that resumes to the tables of
an uninterrupted one."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from physgrad.harness import targets
from physgrad.harness.bench.tuned_report import at_fraction, integrated_profile
from physgrad.harness.cli import main
from physgrad.harness.papers import Target


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_integrated_profile_against_hand_computed_numbers():
    # p1: a 1 s, b 2 s (r = 2), c never; p2: a 3 s (r = 3), b 1 s; p3: nobody.
    times = {"p1": {"a": 1.0, "b": 2.0, "c": math.inf}, "p2": {"a": 3.0, "b": 1.0}, "p3": {"a": math.inf}}
    got = integrated_profile(times, ["a", "b", "c"])
    # B = (1/n) Σ max(0, 4 − r) / 3 over problems with r <= 4
    assert got["a"] == pytest.approx(((4 - 1) + (4 - 3)) / 3 / 3)
    assert got["b"] == pytest.approx(((4 - 2) + (4 - 1)) / 3 / 3)
    assert got["c"] == 0.0
    # the closed form is the integral of the step function ρ(τ) over [1, 4]
    taus = np.linspace(1, 4, 300_001)
    rho = targets.profile(times, ["a", "b"], taus.tolist())
    for m in ("a", "b"):
        assert np.trapezoid(rho[m], taus) / 3 == pytest.approx(got[m], abs=1e-4)


def test_reading_the_runs_at_half_their_budget():
    runs = [{"method": "a", "seed": "0", "status": "reached", "time_to_target": 3.0, "budget_time": 10.0},
            {"method": "a", "seed": "1", "status": "reached", "time_to_target": 6.0, "budget_time": 10.0},
            {"method": "a", "seed": "2", "status": "diverged", "time_to_target": math.inf, "budget_time": math.nan}]  # fmt: skip
    half = at_fraction(runs, 0.5)
    assert [r["status"] for r in half] == ["reached", "censored", "diverged"]
    assert [r["time_to_target"] for r in half] == [3.0, math.inf, math.inf] and half[0]["budget_time"] == 5.0
    assert at_fraction(runs, 1.0) == runs


ARGV = ["bench", "--tuned", "--problems", "hig_toy", "--methods", "adam,hig", "--trials", "2", "--seeds", "2",
        "--steps", "12", "--set", "eval_every=4", "--set", "batch_size=64", "--workers", "1", "--quiet"]  # fmt: skip


@pytest.fixture(scope="module")
def tuned_bench(tmp_path_factory):
    """``physgrad bench --tuned`` on hig_toy: Adam and HIG, 2 trials each, 2 seeds on test."""
    out = tmp_path_factory.mktemp("tuned") / "bench"
    assert main([*ARGV, "--out", str(out)]) == 0
    return out


def _target_between(out: Path) -> float:
    """A target test loss that every run reaches by its end, some earlier than others
    (hig_toy's own, 3e-3, takes far more than 12 steps): the largest of the runs' best losses."""
    best: dict[tuple[str, str], float] = {}
    for r in rows(out / "hig_toy" / "final" / "results.csv"):
        if r["split"] == "test" and r["metric"] == "loss":
            key = (r["method"], r["seed"])
            best[key] = min(best.get(key, math.inf), float(r["value"]))
    return max(best.values())


def _recompute(out: Path, target: float, fraction: float) -> dict[str, tuple[float, float]]:
    """(integrated profile, geo-mean score) per method from summary.csv and results.csv,
    written independently of physgrad.harness.targets (one problem: the fastest method's
    ratio is 1, the others t / fastest; PAR-2 for an unsolved one)."""
    summary = rows(out / "hig_toy" / "final" / "summary.csv")
    results = rows(out / "hig_toy" / "final" / "results.csv")
    axis = "calibrated_time" if results[0].get("calibrated_time") else "wall_time"
    budget_key = "calibrated_seconds" if axis == "calibrated_time" else "train_seconds"
    per_method: dict[str, list[float]] = {}
    budgets = []
    for s in summary:
        budget = float(s[budget_key])
        evals = sorted((int(r["step"]), float(r[axis]), float(r["value"])) for r in results
                       if r["method"] == s["method"] and r["seed"] == s["seed"] and r["split"] == "test"
                       and r["metric"] == "loss")  # fmt: skip
        hit = next((t for _, t, v in evals if v <= target), math.inf)
        if s["status"] == "diverged" or hit > fraction * budget and fraction < 1:
            hit = math.inf
        if s["status"] != "diverged":
            budgets.append(fraction * budget)
        per_method.setdefault(s["method"], []).append(hit)
    medians = {m: float(np.median(v)) for m, v in per_method.items()}
    best = min(medians.values())
    out_ = {}
    for m, t in medians.items():
        if not math.isfinite(best):
            out_[m] = (0.0, math.nan)
            continue
        r = t / best
        integrated = max(0.0, 4 - r) / 3 if r <= 4 else 0.0
        score = r if math.isfinite(r) else max(2 * max(budgets) / best, 1.0)
        out_[m] = (integrated, score)
    return out_


@pytest.mark.costly("a tuned bench end to end (2 methods x (2 trials + 2 seeds) on hig_toy): the one fast-tier run "
                    "of the path; the interrupted resume is in the slow tier")  # fmt: skip
def test_the_leaderboard_equals_a_recomputation_from_the_kept_files(tuned_bench, monkeypatch, capsys):
    out = tuned_bench
    for name in ("bench.json", "bench.md", "leaderboard.csv", "leaderboard.md", "hyperparameters.csv", "profile.csv",
                 "hig_toy/tune.json", "hig_toy/trials.csv", "hig_toy/best.json", "hig_toy/bench_table.csv",
                 "hig_toy/final/summary.csv", "hig_toy/final/results.csv"):  # fmt: skip
        assert (out / name).exists(), name
    assert len(rows(out / "hig_toy" / "trials.csv")) == 4 and len(rows(out / "hig_toy" / "final" / "summary.csv")) == 4
    best = json.loads((out / "hig_toy" / "best.json").read_text())
    hyper = {(h["method"], h["name"]): h for h in rows(out / "hyperparameters.csv")}
    assert float(hyper[("hig", "lr")]["tuned"]) == pytest.approx(best["hig"]["lr"], rel=1e-5)
    assert float(hyper[("hig", "lr")]["untuned"]) == 1.0 and hyper[("hig", "lr")]["trials_finished"] == "2"
    # a target some runs reach, then the report redrawn from the kept files alone
    target = _target_between(out)
    monkeypatch.setattr(targets, "target_of", lambda problem: Target(target, "test", "a level the runs reach"))
    shutil.rmtree(out / "hig_toy" / "trials")  # the trials' run directories are not needed to redraw
    assert main(["report", str(out)]) == 0
    assert "integrated profile" in capsys.readouterr().out
    board = {(r["budget"], r["method"]): r for r in rows(out / "leaderboard.csv")}
    assert {b for b, _ in board} == {"half", "full"}
    for budget, fraction in (("half", 0.5), ("full", 1.0)):
        for method, (integrated, score) in _recompute(out, target, fraction).items():
            row = board[(budget, method)]
            assert float(row["integrated"]) == pytest.approx(integrated, rel=1e-5), (budget, method)
            if math.isnan(score):
                assert row["score"] == ""
            else:
                assert float(row["score"]) == pytest.approx(score, rel=1e-5), (budget, method)
    assert any(float(board[("full", m)]["integrated"]) > 0 for m in ("adam", "hig"))
    effect = {r["method"]: r for r in rows(out / "tuning_effect.csv")}  # what tuning changed, from trials.csv
    for method in ("adam", "hig"):
        mine = [r for r in rows(out / "hig_toy" / "trials.csv") if r["method"] == method and r["state"] == "COMPLETE"]
        assert float(effect[method]["tuned_val_loss"]) == pytest.approx(
            min(float(r["val_loss"]) for r in mine), rel=1e-5
        )
    assert "What tuning changed" in (out / "bench.md").read_text()


def test_the_same_command_again_runs_nothing_and_keeps_the_tables(tuned_bench, capsys):
    out = tuned_bench
    before = {p: (out / p).read_text() for p in ("hig_toy/trials.csv", "hig_toy/final/summary.csv")}
    assert main([*ARGV, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("done already") == 4  # 2 methods x 2 seeds on test; no trial asked again
    assert "trial" not in printed.replace("trials", "")
    assert {p: (out / p).read_text() for p in before} == before


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--problems", "hig_toy", "--trials", "2"], "--trials and --holdout need --tuned"),
        (["--tuned", "--problems", "hig_toy", "--trials", "0"], "--trials must be at least 1"),
        (["--tuned", "--problems", "hig_toy", "--holdout", "1.5"], "--holdout is a fraction in (0, 1)"),
        (["--tuned", "--problems", "hig_toy", "--seconds", "1", "--no-calibrate"], "calibrated step budgets"),
        (["--tuned", "--problems", "hig_toy", "--devices", "2"], "--tuned runs each trial on one device"),
        (["--tuned", "--problems", "nope"], "unknown problem 'nope'"),
        (["--tuned", "--problems", "hig_toy", "--methods", "adam,nope"], "unknown method 'nope'"),
    ],
)
def test_bad_input_is_one_line_exit_2(argv, message, tmp_path, capsys):
    assert main(["bench", *argv, "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "b").exists()


def test_the_report_of_a_tuned_bench_interrupted_before_its_first_problem(tmp_path):
    from physgrad.harness.bench.tuned_report import tuned_report

    info = {"problems": ["hig_toy"], "methods": ["adam", "bptt"], "seeds": [0, 1, 2], "budget": {"seconds": 5.0},
            "settings": {}, "tuned": {"trials": 5, "holdout": 0.2},
            "verdicts": {"hig_toy": [{"method": "adam", "status": "applicable", "reason": ""},
                                     {"method": "bptt", "status": "not applicable", "reason": "no rollout"}]}}  # fmt: skip
    (tmp_path / "bench.json").write_text(json.dumps(info))
    result = tuned_report(tmp_path)
    assert [t["status"] for t in result.tables["hig_toy"]] == ["pending", "not applicable"]
    assert [(b["budget"], b["method"], b["integrated"]) for b in result.board] == [("half", "adam", 0.0),
                                                                                 ("full", "adam", 0.0)]  # fmt: skip
    assert "5 trials per method" in (tmp_path / "bench.md").read_text() and result.hyperparameters == []


def test_what_tuning_changed_against_hand_computed_ranks(tmp_path):
    """tuning_effect.csv's rows from a hand-written trials.csv: trial 0 is the untuned
    configuration, the chosen one the lowest finished trial; a failed trial 0 ranks last."""
    from physgrad.harness.bench.tuned_report import effect_lines, tuning_effect, winners

    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "tune.json").write_text(json.dumps({"methods": ["a", "b", "c", "d"], "spaces": {}}))
    trials = [("a", 0, "COMPLETE", 0.5), ("a", 1, "COMPLETE", 0.1), ("b", 0, "COMPLETE", 0.2),
              ("b", 1, "FAIL", 1e300), ("c", 0, "FAIL", 1e300), ("c", 1, "COMPLETE", 0.3)]  # fmt: skip
    (tmp_path / "p" / "trials.csv").write_text("method,trial,state,val_loss,steps,run_dir,params\n" + "".join(
        f"{m},{t},{state},{loss},10,trials/{m}/trial{t:03d},{{}}\n" for m, t, state, loss in trials))  # fmt: skip
    got = {e["method"]: e for e in tuning_effect(tmp_path, "p")}
    assert set(got) == {"a", "b", "c"}  # d ran no trial
    assert (got["a"]["untuned_val_loss"], got["a"]["tuned_val_loss"], got["a"]["gain"]) == (0.5, 0.1, 5.0)
    assert (got["b"]["tuned_val_loss"], got["b"]["gain"]) == (0.2, 1.0)
    assert math.isinf(got["c"]["untuned_val_loss"]) and math.isinf(got["c"]["gain"])
    assert [(got[m]["rank_untuned"], got[m]["rank_tuned"]) for m in "abc"] == [(2, 1), (1, 2), (None, 3)]
    assert winners(list(got.values())) == ["p: untuned b; tuned a (changed)"]
    assert [line[-1] for line in effect_lines(list(got.values()))[1:]] == ["2 → 1 *", "1 → 2 *", "– → 3 *"]
    assert tuning_effect(tmp_path, "absent") == []
    # a NaN loss (an empty cell) ranks nowhere, equal losses share a rank, a zero loss divides
    (tmp_path / "q").mkdir()
    (tmp_path / "q" / "tune.json").write_text(json.dumps({"methods": ["a", "b", "c", "d"], "spaces": {}}))
    trials = [("a", 0, "COMPLETE", ""), ("b", 0, "COMPLETE", 0.5), ("c", 0, "COMPLETE", 0.5), ("d", 0, "COMPLETE", 0.0),
              ("d", 1, "COMPLETE", 0.0)]  # fmt: skip
    (tmp_path / "q" / "trials.csv").write_text("method,trial,state,val_loss,steps,run_dir,params\n" + "".join(
        f"{m},{t},{state},{loss},10,trials/{m}/trial{t:03d},{{}}\n" for m, t, state, loss in trials))  # fmt: skip
    got = {e["method"]: e for e in tuning_effect(tmp_path, "q")}
    assert [(got[m]["rank_untuned"], got[m]["rank_tuned"]) for m in "abcd"] == [(None, None), (2, 2), (2, 2), (1, 1)]
    assert math.isnan(got["a"]["gain"]) and got["d"]["gain"] == 1.0
    assert winners(list(got.values())) == ["q: untuned d; tuned d (the same)"]
    # nothing finished anywhere: no winner is named
    (tmp_path / "q" / "trials.csv").write_text("method,trial,state,val_loss,steps,run_dir,params\n"
                                               "a,0,FAIL,1e+300,10,trials/a/trial000,{}\n")  # fmt: skip
    assert winners(tuning_effect(tmp_path, "q")) == ["q: untuned none finished; tuned none finished (the same)"]


def test_plan_counts_trials_and_test_runs(tmp_path, capsys):
    assert main(["bench", "--tuned", "--problems", "hig_toy", "--methods", "adam,hig", "--trials", "3", "--seeds", "2",
                 "--seconds", "1", "--plan", "--out", str(tmp_path / "p")]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "3 trials + 2 seeds" in printed and "10 runs" in printed and "nothing was trained" in printed


@pytest.mark.slow  # two tuned benches on two problems, one interrupted and resumed: ~45 s on 2 loaded cores
def test_an_interrupted_tuned_bench_resumes_to_the_same_tables(tmp_path, monkeypatch):
    """Interrupted in its test study (after every trial and one test run), the same command
    again finishes with every table equal to an uninterrupted bench's, given the same
    calibration (copied: a calibration is a measurement, the only thing two benches may differ
    in). The test runs train the trials' calibrated steps (the tune's calibration carried to
    its final/ study)."""
    from physgrad.harness import workers

    argv = ["bench", "--tuned", "--problems", "hig_toy,exp_inverse", "--methods", "adam,hig", "--trials", "2",
            "--seeds", "2", "--seconds", "0.02", "--set", "eval_seconds=0.004", "--set", "hig_toy.batch_size=64",
            "--set", "exp_inverse.n_train=256", "--workers", "1", "--quiet"]  # fmt: skip
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main([*argv, "--out", str(whole)]) == 0
    for problem in ("hig_toy", "exp_inverse"):
        (cut / problem).mkdir(parents=True)
        shutil.copy(whole / problem / "calibration.json", cut / problem / "calibration.json")
        trial_steps = {(r["method"], r["steps"]) for r in rows(whole / problem / "trials.csv")}
        assert {(r["method"], r["steps"]) for r in rows(whole / problem / "final" / "summary.csv")} == trial_steps
    real, calls = workers.ConfiguredRun.__call__, []

    def interrupted(self):
        calls.append(self.run_dir)
        if len(calls) == 11:  # hig_toy's 4 trials and 4 test runs, exp_inverse's first 2 trials, then stop
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(workers.ConfiguredRun, "__call__", interrupted)
    assert main([*argv, "--out", str(cut)]) != 0
    monkeypatch.setattr(workers.ConfiguredRun, "__call__", real)
    assert main([*argv, "--out", str(cut)]) == 0
    for name in ("leaderboard.csv", "hyperparameters.csv", "bench_table.csv", "hig_toy/trials.csv",
                 "exp_inverse/trials.csv", "exp_inverse/final/summary.csv"):  # fmt: skip
        a, b = rows(whole / name), rows(cut / name)
        for r in a + b:  # wall-clock columns and paths are not the result
            for k in [k for k in r if "wall" in k or k in ("train_seconds", "time_per_step", "compile_seconds",
                                                           "ms_per_step", "run_dir", "time", "cpu_time_per_step")]:  # fmt: skip
                r.pop(k)
        assert a == b, name


@pytest.mark.slow  # ~10 s of CPU: two methods tuned and run on test, compiled twice (trial, then test)
def test_a_tuned_run_reaches_the_problems_own_target(tmp_path):
    """On toy2d, a problem optimised directly (validation is its objective), SIP reaches
    the problem's own target (1e-6, not one set for the test) within 30 steps and Adam does
    not: the leaderboard's integrated profile is 1 for SIP and 0 for Adam at the full budget."""
    out = tmp_path / "bench"
    assert main(["bench", "--tuned", "--problems", "toy2d", "--methods", "sip,adam", "--trials", "1", "--seeds", "1",
                 "--steps", "30", "--set", "eval_every=5", "--workers", "1", "--quiet", "--out", str(out)]) == 0  # fmt: skip
    assert targets.target_of("toy2d").loss == 1e-6
    full = {r["method"]: r for r in rows(out / "leaderboard.csv") if r["budget"] == "full"}
    assert float(full["sip"]["integrated"]) == 1.0 and full["sip"]["solved"] == "1"
    assert float(full["adam"]["integrated"]) == 0.0 and full["adam"]["solved"] == "0"

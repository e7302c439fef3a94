"""Calibrated cost, time-to-target and the performance profile, each against an independent
reference: a fake clock for the calibration (so the budgets are exact), hand-computed
curves for time-to-target, a hand-written NumPy Dolan–Moré profile, and the bench's plan
(never running a profile)."""

import csv
import json
import math

import numpy as np
import pytest

import physgrad
from physgrad.harness import bench, targets
from physgrad.harness.bench.applicability import Verdict
from physgrad.harness.bench.estimate import LOOP_SECONDS_PER_STEP, RUN_OVERHEAD_SECONDS, estimate
from physgrad.harness.calibration import (
    CSV_COLUMNS,
    Calibration,
    StageCost,
    calibrate,
    steps_for,
    time_at,
    time_programs,
)
from physgrad.harness.cli import main
from physgrad.harness.config import make_config
from physgrad.harness.papers import PROTOCOLS
from physgrad.harness.registry import PROBLEMS
from physgrad.harness.study import compare


class FakeMachine:
    """A clock that only the fake steps advance, each by its own cost (seconds): the
    calibration's numbers are then exact. ``calls`` records the order of the steps."""

    def __init__(self, costs):
        self.now, self.costs, self.calls = 0.0, costs, []

    def clock(self):
        return self.now

    def step(self, name):
        def run():
            self.calls.append(name)
            self.now += self.costs[name]

        return run

    def programs(self, config):  # calibrate's ``programs``: one fake step per stage, no compilation
        return [self.step(p.method) for p in config.phases], [0.0] * len(config.phases), []


def configs(problem, specs):
    return {s: make_config(problem, s, budget=physgrad.Budget(steps=1)) for s in specs}


def test_time_programs_interleaves_the_methods_and_stops_each_at_its_time_limit():
    machine = FakeMachine({"adam": 0.004, "hig": 0.1})
    programs = {"adam": [machine.step("adam")], "hig": [machine.step("hig")]}
    times = time_programs(programs, repeats=5, max_seconds=math.inf, clock=machine.clock)
    assert machine.calls == ["adam", "hig"] * 5  # one step of every method per round
    assert times == {"adam": [[pytest.approx(0.004)] * 5], "hig": [[pytest.approx(0.1)] * 5]}
    machine.calls.clear()
    times = time_programs(programs, repeats=5, max_seconds=0.25, clock=machine.clock)
    assert len(times["hig"][0]) == 3 and len(times["adam"][0]) == 5  # hig leaves after 3 rounds (0.3 s >= 0.25 s)


def test_a_chunk_of_steps_is_timed_per_step_with_the_steps_it_computed():
    """A program that returns an int took that many steps: its call's seconds are divided by
    them (and its whole call counts towards the time limit); a chunk that stopped at a
    divergent step counts the steps it computed, that one included."""
    machine = FakeMachine({})

    def chunk_of(n, seconds):
        def run():
            machine.now += seconds
            return n

        return run

    times = time_programs({"cheap": [chunk_of(100, 0.01)], "dear": [chunk_of(None, 0.02)]}, repeats=6,
                          max_seconds=0.035, clock=machine.clock)  # fmt: skip
    assert times["cheap"] == [[pytest.approx(1e-4)] * 4]  # a call is 0.01 s: 0.035 s only after the 4th
    assert times["dear"] == [[pytest.approx(0.02)] * 3]  # None: one step; 0.04 s after 2, but 3 rounds at least
    # steps per call: about CALL_SECONDS of them, at most the run's chunk
    from physgrad.engine.step import CHUNK
    from physgrad.harness.calibration import CALL_SECONDS, _chunk_call, chunk_steps

    assert chunk_steps(7e-5) == math.ceil(CALL_SECONDS / 7e-5) and chunk_steps(0.5) == 1
    assert chunk_steps(1e-9) == CHUNK and chunk_steps(0.0) == 1 and chunk_steps(math.nan) == 1
    as_run = lambda taken, diverged: lambda count: (None, None, np.int32(taken), np.bool_(diverged), None)  # noqa: E731
    assert _chunk_call(as_run(7, False), 7) == 7 and _chunk_call(as_run(3, True), 7) == 4


def test_the_chunk_grows_until_a_call_takes_about_ten_milliseconds():
    """A call of n steps costing 0.5 ms of dispatch + n x 0.01 ms: one step reads 0.51 ms per
    step, so the first estimate (20 steps) is still mostly dispatch; the count is measured
    again until a call takes at least half of CALL_SECONDS, and never passes ``longest``."""
    from physgrad.harness.calibration import CALL_SECONDS, sized_chunk

    machine = FakeMachine({})
    calls = []

    def call(n):
        calls.append(n)
        machine.now += 5e-4 + n * 1e-5
        return n

    count = sized_chunk(call, clock=machine.clock)
    assert calls[:2] == [1, 20] and 5e-4 + count * 1e-5 >= CALL_SECONDS / 2 and count > 500
    calls.clear()
    assert sized_chunk(call, longest=40, clock=machine.clock) == 40 and max(calls) == 40


def test_calibrate_times_a_chunk_of_the_runs_loop_on_a_real_problem(monkeypatch):
    """calibrate() on hig_toy: Adam's step (well below a millisecond) is timed in calls of
    the run's own chunks, and the record says so (steps per chunk, the rule, version 4). Calls of
    0.2 s rather than 10 ms: on a loaded machine a one-step call alone can take 10 ms."""
    from physgrad.harness import calibration
    from physgrad.harness.calibration import VERSION, calibrate

    monkeypatch.setattr(calibration, "CALL_SECONDS", 0.2)
    record = calibrate(configs("hig_toy", ["adam"]), repeats=3, echo=lambda *_: None)
    (stage,) = record["methods"]["adam"]["stages"]
    # hig_toy shuffles 4 batches an epoch and evaluates every epoch: the run's chunks are 4 steps
    assert stage["steps_per_call"] == 4 and 0 < stage["seconds"] < 0.01 and stage["rounds"] == 3
    assert "the run's own chunks between evaluations" in record["rule"] and record["version"] == VERSION == 4


def test_calibrated_budgets_are_seconds_over_the_calibrated_step_time():
    machine = FakeMachine({"adam": 0.004, "hig": 0.1})
    record = calibrate(configs("hig_toy", ["adam", "hig", "adam:10,hig"]), repeats=4, clock=machine.clock,
                       programs=machine.programs, echo=lambda line: None)  # fmt: skip
    calibration = Calibration(json.loads(json.dumps(record)))  # as read back from calibration.json
    assert calibration.seconds_per_step("adam") == pytest.approx(0.004)
    assert calibration.steps("adam", 10.0) == 2500  # 10 s / 4 ms
    assert calibration.steps("hig", 10.0) == 100  # 10 s / 100 ms
    # a sequence spends its stages in order: 10 Adam steps (0.04 s), then (10 - 0.04) / 0.1 = 99.6 -> 99 HIG steps
    assert calibration.steps("adam:10,hig", 10.0) == 109
    assert calibration.time_at("adam:10,hig", 109) == pytest.approx(0.04 + 99 * 0.1)
    assert calibration.time_at("hig", 37) == pytest.approx(3.7)  # t = step x calibrated seconds per step
    stage = calibration.stages("hig")[0]
    assert (stage.rounds, stage.q25, stage.q75, stage.batch_size) == (4, pytest.approx(0.1), pytest.approx(0.1), 256)
    assert stage.route == "auto" and calibration.stages("adam")[0].route == ""
    one = StageCost("hig", 1, None, "", 2.0, 2.0, 2.0, 2.0, 2.0, 3)
    assert steps_for(0.5, [one]) == 1 and time_at(3, [one]) == 6.0  # a budget below one step still trains one


def test_the_cpu_clock_does_not_count_a_wait_and_the_record_names_its_clock(monkeypatch):
    """$PHYSGRAD_CALIBRATION_CLOCK=cpu times a step in the process's CPU seconds: a step that
    waits 20 ms (as a step does while a busy neighbour holds the core) costs ~0 on it and
    ≥ 20 ms on the wall clock; a step that computes costs about the same on both. The
    record names its clock; an unknown clock is one line naming the valid ones."""
    import time

    from physgrad.errors import ConfigError

    def busy():  # a fixed amount of Python arithmetic (~10-20 ms of CPU), however loaded the machine
        return sum(i * i for i in range(200_000)) and None

    def programs(config):
        return [busy if config.phases[0].method == "adam" else (lambda: time.sleep(0.02))], [0.0], []

    records = {}
    for name in ("wall", "cpu"):
        monkeypatch.setenv("PHYSGRAD_CALIBRATION_CLOCK", name)
        records[name] = calibrate(configs("hig_toy", ["adam", "hig"]), repeats=3, programs=programs,
                                  echo=lambda line: None)  # fmt: skip
    cost = {name: {m: r["methods"][m]["stages"][0]["seconds"] for m in ("adam", "hig")} for name, r in records.items()}
    assert records["cpu"]["clock"] == "cpu" and records["wall"]["clock"] == "wall"
    assert cost["wall"]["hig"] >= 0.02 and cost["cpu"]["hig"] < 0.005  # the wait is not the step's work
    assert cost["cpu"]["adam"] > 0.002 and cost["wall"]["adam"] >= 0.5 * cost["cpu"]["adam"]  # the work counts
    monkeypatch.setenv("PHYSGRAD_CALIBRATION_CLOCK", "sundial")
    with pytest.raises(ConfigError, match="choose one of wall, cpu"):
        calibrate(configs("hig_toy", ["adam"]), repeats=1, programs=programs, echo=lambda line: None)


def test_a_seconds_study_runs_calibrated_step_budgets_and_a_resume_does_not_time_again(tmp_path):
    machine = FakeMachine({"adam": 0.004, "hig": 0.01})
    out, lines = tmp_path / "study", []
    options = {"programs": machine.programs, "clock": machine.clock, "repeats": 3}
    rows = compare("hig_toy", ["adam", "hig"], [0], physgrad.Budget(seconds=0.05), out, echo=lines.append,
                   settings={"eval_seconds": "0.02"}, calibration_options=options)  # fmt: skip
    steps = {r["method"]: r["steps"] for r in rows}
    assert steps == {"adam": 12, "hig": 5}  # 0.05 s / 4 ms, 0.05 s / 10 ms
    study = json.loads((out / "study.json").read_text())
    assert study["calibrated"] and study["budget"] == {"seconds": 0.05}
    assert study["run_budgets"] == {"adam": {"steps": 12}, "hig": {"steps": 5}}
    config = json.loads(next((out / "runs").glob("adam-*/config.json")).read_text())
    assert config["eval_every"] == 5 and config["eval_seconds"] == 0.0  # 0.02 s at 4 ms per step
    with open(out / "results.csv") as f:
        results = list(csv.DictReader(f))
    for r in results:
        cost = {"adam": 0.004, "hig": 0.01}[r["method"]]
        assert float(r["calibrated_time"]) == pytest.approx(int(r["step"]) * cost)
    summary = {r["method"]: r for r in rows}
    assert summary["hig"]["calibrated_seconds"] == pytest.approx(0.05)
    with open(out / "calibration.csv") as f:
        assert next(csv.reader(f))[: len(CSV_COLUMNS)] == list(CSV_COLUMNS)

    def refuse(config):
        raise AssertionError("a resumed study must not time again")

    lines.clear()
    again = compare("hig_toy", ["adam", "hig"], [0], physgrad.Budget(seconds=0.05), out, echo=lines.append,
                    settings={"eval_seconds": "0.02"}, calibration_options={"programs": refuse})  # fmt: skip
    assert any("reusing" in line for line in lines) and sum("done already" in line for line in lines) == 2
    assert {r["method"]: r["steps"] for r in again} == steps


def test_the_long_study_table_has_the_calibration_columns():
    with open("docs/reproductions/long/calibration.csv") as f:
        assert tuple(next(csv.reader(f))) == CSV_COLUMNS


# --- time-to-target ------------------------------------------------------------------------------


def results_of(method, seed, curve, cost):
    """results.csv rows of one run: test losses at (step, value), calibrated time = step x cost."""
    return [{"method": method, "seed": seed, "step": s, "wall_time": 2 * s * cost, "split": "test", "metric": "loss",
             "value": v, "calibrated_time": s * cost} for s, v in curve]  # fmt: skip


def summary_of(method, seed, status, steps, cost):
    return {"problem": "p", "method": method, "seed": seed, "status": status, "steps": steps,
            "calibrated_seconds": steps * cost, "train_seconds": 2 * steps * cost}  # fmt: skip


def test_time_to_target_is_the_first_evaluation_at_or_below_the_target_with_censoring_and_divergence():
    curve = [(0, 1.0), (10, 0.5), (20, 0.09), (30, 0.05)]  # crosses 0.1 between steps 10 and 20
    results = results_of("a", 0, curve, 0.01)
    results += results_of("a", 1, [(0, 1.0), (10, 0.1), (20, 0.2)], 0.01)  # exactly at the target: reached
    results += results_of("a", 2, [(0, 1.0), (10, 0.5), (20, 0.3)], 0.01)  # never: censored at its budget
    results += results_of("b", 0, [(0, 1.0), (5, 0.01)], 0.01)  # below the target, then diverged: never
    summary = [summary_of("a", 0, "finished", 30, 0.01), summary_of("a", 1, "finished", 20, 0.01),
               summary_of("a", 2, "finished", 20, 0.01), summary_of("b", 0, "diverged", 7, 0.01)]  # fmt: skip
    runs = {(r["method"], r["seed"]): r for r in targets.run_times(summary, results, 0.1)}
    # no interpolation: the evaluation at step 20 (0.2 s), not the crossing near step 18
    assert runs["a", "0"]["status"] == "reached" and runs["a", "0"]["steps_to_target"] == 20
    assert runs["a", "0"]["time_to_target"] == pytest.approx(0.2) and runs["a", "0"]["wall_to_target"] == pytest.approx(
        0.4
    )
    assert runs["a", "1"]["time_to_target"] == pytest.approx(0.1)
    assert runs["a", "2"]["status"] == "censored" and math.isinf(runs["a", "2"]["time_to_target"])
    assert targets.seed_cell(runs["a", "2"]) == ">0.2 s"
    assert runs["b", "0"]["status"] == "diverged" and math.isinf(runs["b", "0"]["time_to_target"])
    table = {t["method"]: t for t in targets.method_times(list(runs.values()), ["a", "b"])}
    assert table["a"]["time"]["median"] == pytest.approx(0.2)  # median of (0.2, 0.1, +inf): the censored seed kept
    assert table["a"]["steps"]["median"] == 20 and table["a"]["reached"] == 2
    assert (
        math.isinf(table["b"]["time"]["median"])
        and targets.median_time_cell(table["b"]) == "never (0/1 reached, 1 diverged)"
    )
    two = [runs["a", "0"], runs["a", "2"], {**runs["a", "2"], "seed": "3"}]  # 1 of 3 reached: the median is +inf
    (row,) = targets.method_times(two, ["a"])
    assert math.isinf(row["time"]["median"]) and targets.median_time_cell(row) == ">0.3 s (>budget) (1/3 reached)"
    # from 3 seeds the median carries its interval: of 3 values a bootstrap median takes the smallest or the
    # largest with probability 7/27 each, so the 95 % percentile interval is [min, max] (∞ for a censored seed)
    three = [runs["a", "0"], runs["a", "1"], {**runs["a", "0"], "seed": "3", "time_to_target": 0.3}]
    (row,) = targets.method_times(three, ["a"])
    assert targets.median_time_cell(row) == "0.2 s [0.1, 0.3] (3/3 reached)"
    (row,) = targets.method_times([runs["a", "0"], runs["a", "1"], runs["a", "2"]], ["a"])
    assert targets.median_time_cell(row) == "0.2 s [0.1, ∞] (2/3 reached)"


def test_every_problem_declares_a_target_with_its_origin():
    for name in PROBLEMS:
        target = PROTOCOLS[name].target
        assert target is not None and target.loss > 0 and target.why, name
        assert target.origin.split(",")[0] in ("paper", "book", "ours"), name


# --- the performance profile -----------------------------------------------------------------------


def dolan_more(T: np.ndarray, taus) -> np.ndarray:
    """Hand-written Dolan–Moré over a (problems x methods) array of times (inf: not solved)."""
    best = T.min(axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        r = np.where(np.isfinite(best), T / best, np.inf)
    return np.array([(r <= tau).mean(axis=0) for tau in taus])  # (taus, methods)


def test_performance_profile_against_a_hand_written_numpy_dolan_more():
    inf = math.inf
    T = np.array([[1.0, 2.0, inf], [10.0, 5.0, 20.0], [inf, inf, inf], [3.0, inf, 3.0], [4.0, 1.0, 8.0]])
    methods = ["a", "b", "c"]
    times = {f"p{i}": dict(zip(methods, row)) for i, row in enumerate(T.tolist())}
    taus = [1.0, 1.5, 2.0, 3.99, 4.0, 10.0, 1e9]
    expected = dolan_more(T, taus)
    got = targets.profile(times, methods, taus)
    for j, m in enumerate(methods):
        assert got[m] == pytest.approx(expected[:, j].tolist())
    assert got["a"][0] == 2 / 5 and got["b"][-1] == 3 / 5  # fastest on p0, p3 (tie with c); b solved 3 of 5
    # the geometric-mean view: over the problems run where some method solved; unsolved = 2 x budget / fastest
    budgets = {p: 100.0 for p in times}
    ran = {m: set(times) for m in methods}
    scores = targets.scores(times, methods, budgets, ran)
    assert scores["a"]["score"] == pytest.approx((1 * 2 * 1 * 4) ** (1 / 4))
    assert scores["b"]["score"] == pytest.approx((2 * 1 * (200 / 3) * 1) ** (1 / 4))
    assert scores["c"]["solved"] == 3 / 5 and scores["c"]["score_problems"] == 4


def test_the_profile_tables_columns_are_the_profile_among_all_methods():
    """ρ(1), ρ(2) and ρ(10) of the leaderboard are each method's ratio to the fastest of all
    the methods (the hand-written NumPy profile), not to itself (which gives ρ(∞) everywhere)."""
    from physgrad.harness.bench.report import profile_board

    inf = math.inf
    T = np.array([[1.0, 3.0, inf], [10.0, 5.0, 20.0], [4.0, 1.0, 8.0]])
    methods = ["a", "b", "c"]
    tables = {f"p{i}": [{"method": m, "status": "finished", "ttt": t, "budget_time": 100.0} for m, t in zip(methods, row)]
              for i, row in enumerate(T.tolist())}  # fmt: skip
    _, _, rows = profile_board(tables)
    expected = dolan_more(T, [1.0, 2.0, 10.0])
    for row in rows:
        j = methods.index(row["method"])
        assert [row["rho1"], row["rho2"], row["rho10"]] == pytest.approx(expected[:, j].tolist()), row["method"]
    c = next(r for r in rows if r["method"] == "c")
    assert (c["rho1"], c["rho2"], c["rho10"], c["solved"]) == (0.0, 0.0, 2 / 3, 2 / 3)  # ratios inf, 4, 8


def test_bench_report_writes_the_profile_and_its_figure(tmp_path):
    out, lines = tmp_path / "bench", []
    result = bench.bench(["hig_toy"], ["adam", "hig"], [0], physgrad.Budget(steps=3), out, echo=lines.append,
                         settings={"eval_every": "1"})  # fmt: skip
    assert (out / "profile.png").exists() and (out / "profile.csv").exists()
    assert (out / "hig_toy" / "time_to_target.csv").exists()
    assert "Performance profile" in (out / "leaderboard.md").read_text()
    assert "Target: test loss ≤ 0.003 (book" in (out / "bench.md").read_text()
    assert {b["method"] for b in result.profile} == {"adam", "hig"} and result.profile_lines[0][0] == "method"


# --- the profiles and their plan ----------------------------------------------------------------


def test_the_named_profiles():
    quick, standard = bench.profile_choice("quick"), bench.profile_choice("standard")
    assert quick["seeds"] >= 3 and standard["seeds"] >= 5 and standard["seconds"] >= 60
    assert set(bench.STANDARD_EXCLUDED) == {"poisson_hig", "navier_stokes"}
    assert set(standard["problems"]) == set(PROBLEMS) - set(bench.STANDARD_EXCLUDED)
    assert not any(".batch_size" in k or k == "batch_size" for k in standard["settings"])  # paper batch sizes


def test_the_plan_estimates_from_the_calibration(tmp_path):
    machine = FakeMachine({"adam": 0.004, "hig": 0.01})
    out = tmp_path / "bench"
    (out / "hig_toy").mkdir(parents=True)
    record = calibrate(configs("hig_toy", ["adam"]), repeats=3, clock=machine.clock, programs=machine.programs,
                       echo=lambda line: None)  # fmt: skip
    (out / "hig_toy" / "calibration.json").write_text(json.dumps(record))
    verdicts = {
        "hig_toy": [Verdict("adam", "applicable"), Verdict("hig", "applicable"), Verdict("sip", "not applicable")]
    }
    (row,) = estimate(["hig_toy"], verdicts, [0, 1, 2], physgrad.Budget(seconds=6.0), out)
    adam = (
        1500 * (0.004 + LOOP_SECONDS_PER_STEP) + RUN_OVERHEAD_SECONDS
    )  # 6 s / 4 ms steps, each with the loop's own time
    hig = 6.0 + RUN_OVERHEAD_SECONDS  # not calibrated: its budget
    assert (row["runs"], row["calibrated"], row["methods"]) == (6, 1, 2)
    assert row["seconds"] == pytest.approx(3 * (adam + hig)) and row["calibration_seconds"] > 0


def test_bench_plan_prints_the_estimate_and_runs_nothing(tmp_path, capsys):
    out = tmp_path / "plan"
    assert main(["bench", "--quick", "--plan", "--problems", "hig_toy,toy2d", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "estimated total:" in printed and "nothing was trained" in printed and "seeds [0, 1, 2]" in printed
    assert "workers" not in printed  # one worker (the suite's default): the total is the wall-clock
    assert not out.exists()


def test_the_plan_on_workers_spreads_the_runs_and_not_the_calibration():
    from physgrad.harness.bench.estimate import wall_seconds

    rows = [{"seconds": 100.0, "calibration_seconds": 10.0}, {"seconds": 30.0, "calibration_seconds": 0.0}]
    assert wall_seconds(rows, 1) == 140.0
    assert wall_seconds(rows, 2) == 10.0 + 50.0 + 15.0
    assert wall_seconds(rows, 4) == 10.0 + 25.0 + 7.5


def test_bench_plan_on_two_workers_prints_their_wall_clock(tmp_path, capsys):
    argv = ["bench", "--quick", "--plan", "--problems", "hig_toy", "--workers", "2", "--out", str(tmp_path / "p")]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "on 2 workers: about" in printed and "of wall-clock at best" in printed


@pytest.mark.parametrize(
    "argv, words",
    [
        (["bench", "--quick", "--standard", "--plan"], "only one of --quick, --standard"),
        (["calibrate", "nosuch"], "valid choices"),
        (["calibrate", "hig_toy", "--out", "x.txt"], "must be a .csv or .json file"),
        (["compare", "hig_toy", "--no-calibrate", "--methods", "nosuch"], "valid choices"),
    ],
)
def test_calibration_options_are_refused_in_one_line(argv, words, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_physgrad_calibrate_writes_the_long_study_table(tmp_path, capsys):
    path = tmp_path / "calibration.csv"
    argv = ["calibrate", "hig_toy", "--methods", "adam", "--repeats", "3", "--max-seconds", "0.001", "--out", str(path)]
    assert main(argv) == 0
    with open(path) as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[: len(CSV_COLUMNS)] == list(CSV_COLUMNS)
    assert (rows[0]["problem"], rows[0]["method"], rows[0]["batch"], rows[0]["rounds"]) == (
        "hig_toy",
        "adam",
        "256",
        "3",
    )
    assert float(rows[0]["ms_per_step"]) > 0 and rows[0]["threads"] == "1" and "calibrate hig_toy" in rows[0]["command"]


def test_compare_calibrate_only_times_and_trains_nothing_and_the_study_then_reuses_it(tmp_path, capsys):
    """``physgrad compare --calibrate-only`` (calibrate on a quiet machine, train anywhere):
    calibration.json and no run; the same study without the flag reuses that record, so
    its runs' step budgets are seconds / the recorded cost."""
    out = tmp_path / "study"
    argv = ["compare", "hig_toy", "--methods", "adam", "--seconds", "0.02", "--out", str(out), "--quiet"]
    assert main([*argv, "--calibrate-only"]) == 0
    printed = capsys.readouterr().out
    assert "nothing was trained" in printed and "adam: adam" in printed
    record = json.loads((out / "calibration.json").read_text())
    assert not (out / "runs").exists() and record["version"] == 4
    cost = record["methods"]["adam"]["stages"][0]["seconds"]
    assert main(argv) == 0
    assert "calibration: reusing" in capsys.readouterr().out
    (run,) = json.loads((out / "study.json").read_text())["run_budgets"].values()
    assert run == {"steps": max(1, math.floor(0.02 / cost))}
    assert main([*argv, "--calibrate-only", "--no-calibrate"]) == 2  # a wall-clock budget has nothing to calibrate
    assert "needs a calibrated --seconds budget" in capsys.readouterr().err


def test_a_wall_cap_stops_a_run_before_its_budget_and_a_larger_cap_resumes_it(tmp_path):
    out, lines = tmp_path / "capped", []
    budget = physgrad.Budget(steps=10**7)
    (row,) = compare("hig_toy", ["adam"], [0], budget, out, echo=lines.append,
                     settings={"wall_cap": "0.3", "eval_every": "50"})  # fmt: skip
    assert row["wall_capped"] and 0 < row["steps"] < 10**7 and row["train_seconds"] >= 0.3
    (run,) = targets.run_times([{**row, "wall_capped": "True"}], [], 1e-30)
    assert run["status"] == "capped" and math.isinf(run["time_to_target"]) and "wall cap" in targets.seed_cell(run)
    names = {p.name for p in (out / "runs").iterdir()}
    lines.clear()
    (same,) = compare("hig_toy", ["adam"], [0], budget, out, echo=lines.append,
                      settings={"wall_cap": "0.3", "eval_every": "50"})  # fmt: skip
    assert "done already" in lines[-1] and same["steps"] == row["steps"]
    (longer,) = compare("hig_toy", ["adam"], [0], budget, out, echo=lines.append,
                        settings={"wall_cap": "0.6", "eval_every": "50"})  # fmt: skip
    assert longer["steps"] > row["steps"] and longer["train_seconds"] >= 0.6
    assert {p.name for p in (out / "runs").iterdir()} == names  # the cap is not part of the run's identity

"""physgrad bench: applicability, the ranking arithmetic, and the command end to end (tiny budgets)."""

import csv
import json
import math
from pathlib import Path

import pytest

import physgrad
from physgrad.harness import bench
from physgrad.harness.bench import Verdict, applicability, leaderboard, method_rows
from physgrad.harness.cli import main
from physgrad.harness.config import split_methods

ROOT = Path(__file__).resolve().parent.parent


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def verdicts_of(problem, methods):
    return {v.method: v for v in applicability(problem, methods)}


def test_applicability_from_the_methods_checks():
    open_loop = verdicts_of("hig_toy", ["adam", "hig", "gn", "sip", "newton", "bptt", "sbptt_c", "one", "wig"])
    assert {m for m, v in open_loop.items() if v.runs} == {"adam", "hig", "gn", "newton"}
    assert open_loop["bptt"].status == open_loop["one"].status == "not applicable"
    assert "rollout" in open_loop["bptt"].reason and "time-stepper" in open_loop["wig"].reason
    assert "target" in open_loop["sip"].reason  # hig_toy defines no y-space target
    oscillators = verdicts_of("oscillators", ["hig", "sip", "bptt"])
    assert oscillators["hig"].runs and oscillators["sip"].runs and not oscillators["bptt"].runs
    closed_loop = verdicts_of("cartpole", ["bptt", "no_temporal", "adam", "one"])
    assert closed_loop["bptt"].runs and closed_loop["no_temporal"].runs and closed_loop["adam"].runs
    assert not closed_loop["one"].runs
    # newton's dense Hessian on a ~9.5k-parameter network: skipped by the bench's policy, with the reason
    dipole = verdicts_of("quantum_dipole", ["newton"])["newton"]
    assert dipole.status == "skipped" and "9484" in dipole.reason


def test_applicability_sees_the_batch_size_and_scoped_settings():
    (v,) = applicability("toy2d", ["adam"], {"batch_size": "4"})  # toy2d has one training sample
    assert v.status == "not applicable" and "exceeds" in v.reason
    (v,) = applicability("toy2d", ["adam"], {"hig_toy.batch_size": "4"})  # scoped to another problem
    assert v.runs


def test_method_lists_keep_colon_names_apart_from_sequences():
    assert split_methods("adam,optax:lion,adam:2000,hig") == ["adam", "optax:lion", "adam:2000,hig"]
    assert split_methods(" adam , hig ,") == ["adam", "hig"]
    quick = bench.quick_settings(["oscillators", "sine"], ["adam", "hig"])
    assert quick["oscillators.hig.batch_size"] == "32" and "oscillators.gn.batch_size" not in quick
    assert "exp_inverse.n_train" not in quick and quick["sine.n_train"] == "4096" and quick["eval_seconds"] == "0.5"
    assert bench.problem_settings("sine", "adam", {"sine.n_train": "64", "toy2d.start": "1", "lr": "0.1",
                                                   "sine.hig.lr": "2", "adam.eps": "1e-8"}) == {
        "n_train": "64", "lr": "0.1", "adam.eps": "1e-8"}  # fmt: skip


def fake_study():
    """Two problems, hand-computed: p1 adam {1, 3} (median 2, std √2), hig {0.5, 1.5}
    (median 1), sgd {0.1 finished, one diverged: +∞} (median ∞); p2 adam {4}, hig failed
    (refused), sgd {1}. Seeds 0 and 1, in that order."""
    p1 = [
        {"method": "adam", "seed": "0", "status": "finished", "final_test_loss": "1.0"},
        {"method": "adam", "seed": "1", "status": "finished", "final_test_loss": "3.0"},
        {"method": "hig", "seed": "0", "status": "finished", "final_test_loss": "0.5"},
        {"method": "hig", "seed": "1", "status": "finished", "final_test_loss": "1.5"},
        {"method": "sgd", "seed": "0", "status": "finished", "final_test_loss": "0.1"},
        {"method": "sgd", "seed": "1", "status": "diverged", "final_test_loss": ""},
    ]
    p2 = [
        {"method": "adam", "seed": "0", "status": "finished", "final_test_loss": "4.0"},
        {"method": "sgd", "seed": "0", "status": "finished", "final_test_loss": "1.0"},
    ]
    v = lambda *names: [Verdict(n, "applicable") for n in names]  # noqa: E731
    t1 = method_rows(p1, v("adam", "hig", "sgd") + [Verdict("bptt", "not applicable", "no rollout")])
    t2 = method_rows(
        p2, v("adam", "hig", "sgd"), failures={"hig-seed0-x": {"method": "hig", "seed": 0, "error": "refused"}}
    )
    return {"p1": t1, "p2": t2}


def test_ranks_ratios_and_leaderboard_against_hand_computed_numbers():
    tables = fake_study()
    t1 = {t["method"]: t for t in tables["p1"]}
    assert (
        t1["adam"]["median"] == 2.0 and t1["adam"]["mean"] == 2.0 and t1["adam"]["std"] == pytest.approx(math.sqrt(2))
    )
    assert t1["hig"]["median"] == 1.0 and t1["hig"]["ratio"] == 0.5  # median of the per-seed ratios 0.5, 0.5
    # sgd's finished seed is the lowest, but its other seed diverged: a failure, +∞, never the survivor's 0.1
    assert t1["sgd"]["median"] == math.inf and t1["sgd"]["mean"] == math.inf and t1["sgd"]["diverged"] == 1
    assert t1["sgd"]["ratio"] == math.inf  # median of the per-seed ratios 0.1 and ∞
    assert (t1["hig"]["rank"], t1["adam"]["rank"], t1["sgd"]["rank"]) == (1, 2, 3)
    assert t1["bptt"]["status"] == "not applicable" and t1["bptt"]["rank"] is None and math.isnan(t1["bptt"]["ratio"])
    t2 = {t["method"]: t for t in tables["p2"]}
    assert t2["hig"]["status"] == "failed" and t2["hig"]["failed"] == 1 and t2["hig"]["rank"] is None
    assert (t2["sgd"]["rank"], t2["adam"]["rank"], t2["sgd"]["ratio"]) == (1, 2, 0.25)
    board = {b["method"]: b for b in leaderboard(tables)}
    # sgd's ∞ on p1 enters as the clipped worst ratio
    assert board["sgd"]["geomean_ratio"] == pytest.approx(math.sqrt(1e6 * 0.25))
    assert board["hig"]["geomean_ratio"] == 0.5 and board["hig"]["ratio_problems"] == 1  # p2 failed: no ratio
    assert board["adam"]["geomean_ratio"] == 1.0
    tables["p2"][2]["ratio"] = 0.0  # a loss of exactly 0: clipped in the logarithm, not -inf
    assert {b["method"]: b for b in leaderboard(tables)}["sgd"]["geomean_ratio"] == pytest.approx(1.0)
    assert (board["hig"]["wins"], board["sgd"]["wins"], board["adam"]["wins"]) == (1, 1, 0)
    assert (board["sgd"]["divergences"], board["hig"]["failures"], board["hig"]["problems"]) == (1, 1, 2)
    assert "bptt" not in board  # never applicable: not on the leaderboard
    # the score counts hig's failed problem as the worst ratio: √(0.5 · 1e6)
    assert board["hig"]["score"] == pytest.approx(math.sqrt(0.5 * 1e6))
    assert board["sgd"]["score"] == board["sgd"]["geomean_ratio"] and board["adam"]["score"] == 1.0
    assert [b["method"] for b in leaderboard(fake_study())] == ["adam", "sgd", "hig"]
    lines = {line[1]: line for line in bench.table_lines(tables["p1"])[1:]}
    assert lines["sgd"][3] == "∞ [n/a: 2 seeds]" and lines["sgd"][4] == "∞" and "1 of 2 diverged" in lines["sgd"][6]
    assert lines["adam"][3] == "2.000e+00 [n/a: 2 seeds]"


def test_paired_test_rows_are_read_against_the_best():
    table = fake_study()["p1"]
    tests = [{"method_a": "hig", "method_b": "adam", "pairs": 8, "seeds": 2, "seeds_a_lower": 2,
              "p_value": math.nan}]  # fmt: skip
    table = {t["method"]: t for t in bench.add_paired_tests(table, tests)}
    assert table["adam"]["best"] == "hig" and math.isnan(table["adam"]["p_vs_best"])  # 2 seeds: no p-value
    assert table["adam"]["seeds_best_lower"] == 2 and table["adam"]["seeds_compared"] == 2
    assert math.isnan(table["hig"]["p_vs_best"]) and table["sgd"]["pairs"] == 0
    lines = {line[1]: line for line in bench.table_lines(list(table.values()))[1:]}
    assert lines["adam"][5] == "n/a: 2 seeds (2/2)" and lines["hig"][5] == "best"


def test_heatmap_marks_failed_and_blank_cells(tmp_path):
    path = bench.heatmap(fake_study(), tmp_path / "h.png")
    assert path.exists() and path.stat().st_size > 1000


def test_a_failing_run_is_recorded_and_the_problem_goes_on(tmp_path, monkeypatch):
    import physgrad.harness.study.running
    from physgrad.errors import DoesNotFit

    real = physgrad.harness.study.running.train  # the one run loop: study.compare's

    def refuse_hig(config, run_dir, **kwargs):
        if config.method == "hig":  # the memory guard's refusal (a ConfigError, but the machine's, not the input's)
            raise DoesNotFit("hig step needs ~1 TiB; would fit: batch_size=1")
        return real(config, run_dir, **kwargs)

    monkeypatch.setattr(physgrad.harness.study.running, "train", refuse_hig)
    lines = []
    verdicts = [Verdict("adam", "applicable"), Verdict("hig", "applicable")]
    out = tmp_path / "toy2d"
    summary = bench.run_problem("toy2d", verdicts, [0], physgrad.Budget(steps=2), out, echo=lines.append)
    assert [r["method"] for r in summary] == ["adam"]
    failures = json.loads((out / "failures.json").read_text())
    assert [f["method"] for f in failures.values()] == ["hig"] and "1 TiB" in next(iter(failures.values()))["error"]
    assert any("failed, recorded" in line for line in lines)
    assert all(line.startswith("toy2d [") for line in lines)  # compare's lines, with the problem in front
    table = {t["method"]: t for t in bench.problem_table(out, verdicts)}
    assert table["hig"]["status"] == "failed" and table["adam"]["rank"] == 1


# --- study.compare's failure log: the bench's run loop ---------------------------------------


def fail_on(monkeypatch, error, method="hig", seed=None):
    """study.compare's train raising ``error`` for one method (one seed of it, where given);
    returns the list of (method, seed) that train was called with."""
    import physgrad.harness.study.running
    from physgrad.harness.train import train as real  # study's own, also where an earlier call patched it

    calls = []

    def train(config, run_dir, **kwargs):
        calls.append((config.method, config.seed))
        if config.method == method and seed in (None, config.seed):
            raise error
        return real(config, run_dir, **kwargs)

    monkeypatch.setattr(physgrad.harness.study.running, "train", train)
    return calls


def test_compare_records_a_failing_seed_and_finishes_the_other_runs(tmp_path, monkeypatch):
    from physgrad.harness.study import compare

    calls = fail_on(monkeypatch, RuntimeError("the solver\nbroke"), seed=1)
    lines, out = [], tmp_path / "study"
    rows = compare("toy2d", ["hig", "adam"], [0, 1], physgrad.Budget(steps=2), out, echo=lines.append,
                   record_failures=True)  # fmt: skip
    assert calls == [("hig", 0), ("hig", 1), ("adam", 0), ("adam", 1)]  # the runs after the failure still ran
    assert sorted((r["method"], r["seed"]) for r in rows) == [("adam", 0), ("adam", 1), ("hig", 0)]
    (name, entry), *others = bench.read_failures(out).items()
    assert not others and (entry["method"], entry["seed"]) == ("hig", 1)
    assert entry["error"] == "RuntimeError: the solver broke"  # one line
    trace = (out / entry["traceback"]).read_text()
    assert entry["traceback"] == f"runs/{name}/traceback.txt" and "Traceback" in trace and "the solver" in trace
    assert "[2/4] hig seed 1: failed, recorded (RuntimeError: the solver broke)" in lines
    # again, with the cause gone: the finished runs are skipped, the failed one runs and leaves the log
    calls = fail_on(monkeypatch, RuntimeError("never"), method="none")
    lines = []
    rows = compare("toy2d", ["hig", "adam"], [0, 1], physgrad.Budget(steps=2), out, echo=lines.append,
                   record_failures=True)  # fmt: skip
    assert calls == [("hig", 1)] and sum("done already" in line for line in lines) == 3 and len(rows) == 4
    assert bench.read_failures(out) == {} and not (out / "runs" / name / "traceback.txt").exists()


def test_a_config_error_or_an_interrupt_still_stops_the_study(tmp_path, monkeypatch):
    from physgrad.harness.study import compare

    budget = physgrad.Budget(steps=2)
    for error in (physgrad.ConfigError("lr must be positive"), KeyboardInterrupt()):
        calls = fail_on(monkeypatch, error)
        with pytest.raises(type(error)):
            compare("toy2d", ["hig", "adam"], [0], budget, tmp_path / "s", echo=lambda line: None,
                    record_failures=True)  # fmt: skip
        assert calls == [("hig", 0)]  # stopped: adam never ran
        assert bench.read_failures(tmp_path / "s") == {}  # and nothing was recorded as the method's failure
    # without record_failures, the first error of any kind stops the study (compare's default)
    calls = fail_on(monkeypatch, RuntimeError("boom"))
    with pytest.raises(RuntimeError, match="boom"):
        compare("toy2d", ["hig", "adam"], [0], budget, tmp_path / "plain", echo=lambda line: None)
    assert calls == [("hig", 0)] and not (tmp_path / "plain" / "failures.json").exists()


def test_the_memory_guards_refusal_is_recorded_not_raised(tmp_path, monkeypatch):
    """The real guard (a ConfigError subclass, DoesNotFit) refuses each seed: both recorded, the study goes on."""
    from physgrad.engine import memory
    from physgrad.harness.study import compare

    monkeypatch.setattr(memory, "available_bytes", lambda device=None: 1000)
    lines, out = [], tmp_path / "study"
    assert compare("hig_toy", ["hig"], [0, 1], physgrad.Budget(steps=1), out, echo=lines.append,
                   record_failures=True) == []  # fmt: skip
    failures = bench.read_failures(out)
    assert sorted(f["seed"] for f in failures.values()) == [0, 1]
    assert all(f["error"].startswith("DoesNotFit: hig step needs") for f in failures.values())
    assert sum("failed, recorded" in line for line in lines) == 2


def test_each_method_of_a_problem_study_gets_the_bench_settings():
    """bench hands compare the problem's settings (study_settings); compare's own resolution
    must give every run the configuration the bench asked for (the same run names, so a
    bench directory written before resumes)."""
    from physgrad.harness.config import make_config
    from physgrad.harness.study import plan

    methods, problems = (
        [*bench.QUICK["methods"], "sgd"],
        ["hig_toy", "sine", "oscillators"],
    )  # the quick profile's scopes
    settings = {**bench.quick_settings(problems, methods), "hig_toy.sgd.lr": "0.5", "lr": "0.01",
                "adam.eps": "1e-7", "oscillators.batch_size": "16"}  # fmt: skip
    verdicts = bench.plan(problems, methods, settings)
    budget = physgrad.Budget(seconds=10)
    for problem, vs in verdicts.items():
        runs = [v.method for v in vs if v.runs]
        planned = plan(problem, runs, [0, 1], budget, bench.study_settings(problem, runs, settings))
        expected = [make_config(problem, m, budget=budget, seed=s, settings=bench.problem_settings(problem, m, settings))
                    for m in runs for s in (0, 1)]  # fmt: skip
        assert planned == expected, problem
    assert bench.study_settings("oscillators", ["adam", "hig"], settings) == {
        "eval_seconds": "0.5", "hig.batch_size": "32", "lr": "0.01", "adam.eps": "1e-7", "batch_size": "16"}  # fmt: skip


@pytest.mark.slow
def test_bench_cli_end_to_end_and_resume(tmp_path, capsys):
    out = tmp_path / "bench"
    argv = ["bench", "--problems", "hig_toy,toy2d", "--methods", "adam,sgd,bptt", "--steps", "3", "--seeds", "1",
            "--out", str(out), "--quiet", "--set", "hig_toy.batch_size=64", "--set", "hig_toy.sgd.lr=1e12"]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "leaderboard" in printed and "not applicable" in printed
    for name in ("bench.md", "bench.json", "leaderboard.csv", "leaderboard.md", "heatmap.png", "bench_table.csv",
                 "hig_toy/bench_table.csv", "hig_toy/bench_table.md", "hig_toy/summary.csv", "hig_toy/study.json",
                 "toy2d/bench_table.csv", "toy2d/loss_vs_time.png"):  # fmt: skip
        assert (out / name).exists(), name
    table = {r["method"]: r for r in rows(out / "hig_toy" / "bench_table.csv")}
    assert table["sgd"]["status"] == "diverged" and table["sgd"]["diverged"] == "1" and table["sgd"]["rank"] == ""
    assert table["adam"]["rank"] == "1" and float(table["adam"]["ratio_to_adam"]) == 1.0
    assert table["bptt"]["status"] == "not applicable"
    board = {r["method"]: r for r in rows(out / "leaderboard.csv")}
    assert (
        board["sgd"]["divergences"] == "1"
        and board["sgd"]["runs"] == "2"
        and board["adam"]["problems"] == "2"
        and "bptt" not in board
    )
    markdown = (out / "bench.md").read_text()
    assert "3 training steps per run" in markdown and "CPU cores" in markdown and "JAX" in markdown
    assert "Wilcoxon" in markdown and "physgrad bench --seconds 600 --seeds 5" in markdown
    assert "hig_toy.batch_size=64" in markdown
    # the same command again: every run is skipped, the report is rewritten
    assert main(argv) == 0
    assert capsys.readouterr().out.count("done already") == 4  # 2 problems x 2 methods x 1 seed
    # kept without its runs (docs/reproductions/keep_studies.py), the bench is redrawn from its files
    import importlib.util

    spec = importlib.util.spec_from_file_location("keep_studies", ROOT / "docs/reproductions/keep_studies.py")
    keep_studies = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(keep_studies)
    for runs in (False, True):
        kept = tmp_path / f"kept-{runs}"
        keep_studies.keep(out, kept, runs=runs)
        assert main(["report", str(kept)]) == 0 and "leaderboard" in capsys.readouterr().out
        for problem in ("hig_toy", "toy2d"):
            again = {r["method"]: r for r in rows(kept / problem / "bench_table.csv")}
            first = {r["method"]: r for r in rows(out / problem / "bench_table.csv")}
            assert again == first, (problem, runs)
        assert rows(kept / "leaderboard.csv") == rows(out / "leaderboard.csv")


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--problems", "hig_toy,nope"], "unknown problem 'nope'; valid choices: advection_1d, cartpole,"),
        (["--problems", "hig_toy", "--methods", "adam,nope"], "unknown method 'nope'; valid choices:"),
        (["--problems", "hig_toy", "--set", "nope=1"], "unknown setting 'nope'; valid choices:"),
        (["--problems", "hig_toy", "--set", "toy2d.lr=1"], "unknown problem in a scoped setting 'toy2d'"),
        (["--problems", "hig_toy", "--seeds", "0"], "--seeds must be at least 1"),
        (["--problems", "hig_toy", "--steps", "1", "--seconds", "1"], "only one of"),
    ],
)
def test_bad_input_is_one_line_exit_2(argv, message, tmp_path, capsys):
    assert main(["bench", *argv, "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "b").exists()  # nothing ran or was written


def test_report_of_a_bench_interrupted_before_a_problem(tmp_path):
    info = {"problems": ["toy2d"], "methods": ["adam", "bptt"], "seeds": [0], "budget": {"seconds": 5.0},
            "settings": {}, "verdicts": {"toy2d": [{"method": "adam", "status": "applicable", "reason": ""},
                                                   {"method": "bptt", "status": "not applicable", "reason": "no rollout"}]}}  # fmt: skip
    (tmp_path / "bench.json").write_text(json.dumps(info))
    result = bench.report(tmp_path)
    assert [t["status"] for t in result.tables["toy2d"]] == ["pending", "not applicable"]
    assert (tmp_path / "toy2d" / "bench_table.md").exists() and (tmp_path / "heatmap.png").exists()
    text = (tmp_path / "bench.md").read_text()
    assert "5 s of training wall-clock per run" in text
    assert "toy2d/loss_vs_time.png" not in text and "none yet" in text  # no link to a figure not drawn

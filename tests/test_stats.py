"""Statistics over seeds: the seeds are the replicates, a diverged seed is a failure (+∞)
counted in every aggregate, and no p-value is printed where the seed count cannot support
one; p-values print as numbers that never read as a bare 0 or 1.

The study directories here are written file by file in the layout a run leaves behind
(``config.json``, ``summary.json``, ``metrics.csv``, ``test_cases.json``) and gathered by
``study.collect``, so the statistics read exactly what a real study would give them. The
expected numbers come from the test's own arrays, ``scipy.stats.wilcoxon`` on the per-seed
differences, and an independent NumPy percentile bootstrap.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from scipy.stats import wilcoxon

from physgrad.harness import seeds as seedstats
from physgrad.harness.stats import (
    COLUMNS,
    MIN_SEEDS_P,
    case_spread,
    case_values,
    format_p,
    format_tests,
    paired_tests,
    seed_means,
    signed_rank_p,
)
from physgrad.harness.study import collect, report

CASES = 20


def write_run(study, method, seed, status, values, metric="rel_error", final=1.0):
    """One run directory as training leaves it; a diverged run also has test cases (from
    its last finite parameters), which is what must not enter the pairs."""
    run = study / "runs" / f"{method}-seed{seed}-0000"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"problem": "toy", "method": method, "seed": seed}))
    diverged = status == "diverged"
    (run / "summary.json").write_text(json.dumps({
        "status": status, "steps": 10, "epochs": 1.0, "train_seconds": 1.0, "time_per_step": 0.1,
        "final_train_loss": None if diverged else 1.0, "final_test_loss": None if diverged else final,
        "best_test_loss": 1.0, "diverged_step": 7 if diverged else None,
        "last_finite_loss": 1e28 if diverged else None, "compile_seconds": 0.5,
    }))  # fmt: skip
    (run / "metrics.csv").write_text("step,wall_time,split,metric,value\n10,1.0,test,loss,1.0\n")
    values = [float(v) for v in values]
    (run / "test_cases.json").write_text(json.dumps({metric: values, "loss": values}))


def reference_arrays(seed):
    """Per-case values of a well-behaved pair: b is about twice a, with noise."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(1.0, 2.0, CASES)
    return a, 2.0 * a + rng.normal(0.0, 0.3, CASES)


def read_rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def per_seed_means(seeds):
    """Each seed's mean over its cases for (a, b) of reference_arrays."""
    return [(float(np.mean(reference_arrays(s)[0])), float(np.mean(reference_arrays(s)[1]))) for s in seeds]


def test_a_diverged_seed_is_a_failure_in_the_pairs_not_left_out(tmp_path):
    for seed in (0, 1, 2):
        a, b = reference_arrays(seed)
        write_run(tmp_path, "adam", seed, "finished", a)
        if seed == 1:  # the demo's case: one GN seed blew up to astronomical values
            write_run(tmp_path, "gn", seed, "diverged", np.full(CASES, 1e28))
        else:
            write_run(tmp_path, "gn", seed, "finished", b)
    summary = collect(tmp_path)
    assert {(r["method"], r["seed"]): r["status"] for r in summary}[("gn", 1)] == "diverged"

    metric, values = case_values(tmp_path)
    assert metric == "rel_error" and sorted(values["gn"]) == [0, 2] and sorted(values["adam"]) == [0, 1, 2]
    assert seed_means(tmp_path)["gn"][2] == 2  # the per-case helper: finished runs only, documented

    (row,) = paired_tests(tmp_path, order=["adam", "gn"])
    (a0, b0), (a2, b2) = per_seed_means([0, 2])
    # seed 1: adam's value against gn's failure (+inf): adam lower, per-seed ratio 0
    assert row["seeds"] == 3 and row["seeds_a_lower"] == 3 and row["ties"] == 0
    assert row["ratio"] == pytest.approx(min(a0 / b0, a2 / b2), rel=1e-12)  # the median of (r0, 0, r2)
    assert math.isnan(row["p_value"]) and row["tested"] == 3  # 3 seeds: 2/2^3 = 0.25 at best, no p-value
    assert row["pairs"] == 2 * CASES  # the (seed, case) pairs inside the finished seeds' means
    assert (row["runs_a"], row["diverged_a"], row["runs_b"], row["diverged_b"], row["dropped"]) == (3, 0, 3, 1, 0)
    assert "1e+28" not in json.dumps(row) and row["ratio"] < 1

    # The file: original columns first and in their order, then the additions.
    with open(tmp_path / "paired_tests.csv") as f:
        header = next(csv.reader(f))
    assert tuple(header[:9]) == ("metric", "method_a", "method_b", "pairs", "a_lower", "seeds", "seeds_a_lower",
                                 "ratio", "p_value")  # fmt: skip
    assert tuple(header) == COLUMNS
    (written,) = read_rows(tmp_path / "paired_tests.csv")
    assert float(written["ratio"]) == pytest.approx(row["ratio"], rel=1e-12) and written["p_value"] == "nan"
    assert int(written["seeds"]) == 3 and int(written["diverged_b"]) == 1

    head, line = format_tests([row])
    cells = dict(zip(head, line))
    assert cells["diverged"] == "gn 1 of 3" and cells["first lower"] == "3/3" and cells["seeds"] == "3"
    assert cells["ratio, median [95% CI]"].startswith(f"{row['ratio']:.3g} [0, ")
    assert cells["Wilcoxon p"] == "n/a: 3 seeds (min p 0.25)"


def test_every_seed_diverged_loses_every_pair_and_two_failures_tie(tmp_path):
    for seed in (0, 1):
        a, b = reference_arrays(seed)
        write_run(tmp_path, "adam", seed, "finished", a)
        write_run(tmp_path, "gn", seed, "diverged", np.full(CASES, 1e28))
        write_run(tmp_path, "sgd", seed, "diverged", np.full(CASES, 1e30))
        write_run(tmp_path, "hig", seed, "finished", b)
    collect(tmp_path)
    rows = {(r["method_a"], r["method_b"]): r for r in paired_tests(tmp_path, order=["adam", "gn", "sgd", "hig"])}
    assert rows[("adam", "gn")]["seeds"] == 2 and rows[("adam", "gn")]["seeds_a_lower"] == 2
    assert rows[("adam", "gn")]["ratio"] == 0.0 and rows[("gn", "hig")]["ratio"] == math.inf
    assert rows[("gn", "sgd")]["ties"] == 2 and rows[("gn", "sgd")]["ratio"] == 1.0  # two failures tie
    assert rows[("gn", "sgd")]["tested"] == 0 and rows[("gn", "sgd")]["seeds_a_lower"] == 0
    lines = format_tests(list(rows.values()))
    by_pair = {line[0]: dict(zip(lines[0], line)) for line in lines[1:]}
    assert by_pair["gn vs hig"]["ratio, median [95% CI]"] == "∞ [n/a: 2 seeds]"
    assert by_pair["gn vs hig"]["diverged"] == "gn 2 of 2" and by_pair["adam vs hig"]["diverged"] == "-"
    assert by_pair["gn vs sgd"]["first lower"] == "0/2 (2 tied)"
    assert by_pair["gn vs sgd"]["Wilcoxon p"] == "n/a: no seed differs"
    for cells in by_pair.values():
        assert cells["Wilcoxon p"].startswith("n/a")


def test_non_finite_cases_of_finished_runs_are_dropped_and_counted(tmp_path):
    a, b = reference_arrays(0)
    b_broken = b.copy()
    b_broken[[3, 11]] = [np.inf, np.nan]
    write_run(tmp_path, "adam", 0, "finished", a)
    write_run(tmp_path, "gn", 0, "finished", b_broken)
    collect(tmp_path)
    (row,) = paired_tests(tmp_path, order=["adam", "gn"])
    keep = np.isfinite(b_broken)
    assert row["pairs"] == CASES - 2 and row["dropped"] == 2 and row["seeds"] == 1
    assert row["ratio"] == pytest.approx(np.mean(a[keep]) / np.mean(b[keep]), rel=1e-12)
    assert row["a_lower"] == pytest.approx(np.mean(a[keep] < b[keep]))
    _, line = format_tests([row])
    assert "1 (2 non-finite cases dropped)" in line


def test_a_zero_loss_gives_an_infinite_ratio(tmp_path):
    a, _ = reference_arrays(0)
    write_run(tmp_path, "adam", 0, "finished", a)
    write_run(tmp_path, "exact", 0, "finished", np.zeros(CASES))
    collect(tmp_path)
    (row,) = paired_tests(tmp_path, order=["adam", "exact"])
    assert row["ratio"] == math.inf and row["seeds"] == 1
    head, line = format_tests([row])
    assert dict(zip(head, line))["ratio, median [95% CI]"] == "∞ [n/a: 1 seed]"


def test_thousands_of_test_cases_of_one_seed_give_no_p_value(tmp_path):
    """Pseudo-replication: 2,000 cases of one seed once printed Wilcoxon p <1e-300; they share
    one network, so they are one replicate."""
    rng = np.random.default_rng(1)
    a = rng.uniform(1.0, 2.0, 2000)
    b = a + rng.uniform(0.5, 1.0, 2000)
    write_run(tmp_path, "adam", 0, "finished", a)
    write_run(tmp_path, "gn", 0, "finished", b)
    collect(tmp_path)
    (row,) = paired_tests(tmp_path, order=["adam", "gn"])
    assert math.isnan(row["p_value"]) and row["pairs"] == 2000 and row["seeds"] == 1
    head, line = format_tests([row])
    assert dict(zip(head, line))["Wilcoxon p"] == "n/a: 1 seed (min p 1)"


def test_wilcoxon_over_seeds_from_six_seeds_on(tmp_path):
    """8 seeds, one diverged in b: the test is scipy's signed-rank test of the per-seed
    differences, the failure entering as the largest difference (only ranks count)."""
    seeds = range(8)
    for seed in seeds:
        a, b = reference_arrays(seed)
        write_run(tmp_path, "a", seed, "finished", a)
        write_run(tmp_path, "b", seed, "diverged" if seed == 5 else "finished", b)
    collect(tmp_path)
    (row,) = paired_tests(tmp_path, order=["a", "b"])
    d = [x - y for x, y in per_seed_means(seeds)]
    d[5] = -1e6  # a lower, by more than any finished seed's difference
    assert row["seeds"] == 8 and row["tested"] == 8 and row["seeds_a_lower"] == 8
    assert row["p_value"] == pytest.approx(wilcoxon(d).pvalue, rel=1e-12)
    assert row["p_value"] == pytest.approx(2 / 2**8)  # every seed lower: the exact test's smallest p
    p, n = signed_rank_p(np.array([1.0, -2.0, 3.0, 0.0, 4.0, 5.0]))
    assert math.isnan(p) and n == 5  # a tie leaves 5 seeds: no p-value
    p, n = signed_rank_p(np.array([1.0, -2.0, 3.0, 4.0, 5.0, 6.0]))
    assert n == MIN_SEEDS_P and p == pytest.approx(wilcoxon([1.0, -2.0, 3.0, 4.0, 5.0, 6.0]).pvalue)


def test_status_falls_back_to_the_run_summary(tmp_path):
    """A summary.csv without a status column (written by hand or by an older version):
    each run's summary.json decides, and a run with neither counts as finished."""
    rows = ["problem,method,seed,run_dir"]
    for method, seed, status in (
        ("a", 0, "finished"),
        ("a", 1, "finished"),
        ("b", 0, "finished"),
        ("b", 1, "diverged"),
    ):
        write_run(tmp_path, method, seed, status, np.arange(1.0, CASES + 1) + (method == "b"))
        rows.append(f"toy,{method},{seed},runs/{method}-seed{seed}-0000")
    (tmp_path / "runs" / "a-seed1-0000" / "summary.json").unlink()
    (tmp_path / "summary.csv").write_text("\n".join(rows) + "\n")
    _, values = case_values(tmp_path)
    assert sorted(values["a"]) == [0, 1] and sorted(values["b"]) == [0]
    (row,) = paired_tests(tmp_path)
    assert row["pairs"] == CASES and row["diverged_b"] == 1 and row["seeds"] == 2 and row["seeds_a_lower"] == 2


def test_a_two_seed_study_prints_no_p_value(tmp_path):
    """The command line's table (compare, report, demo) is built from format_tests."""
    from rich.console import Console

    from physgrad.harness.study.console import print_paired_tests as _print_paired_tests

    for seed in (0, 1):
        a, b = reference_arrays(seed)
        write_run(tmp_path, "adam", seed, "finished", a)
        write_run(tmp_path, "hig", seed, "finished", b)
        write_run(tmp_path, "gn", seed, "diverged", np.full(CASES, 1e28))
    collect(tmp_path)
    console = Console(record=True, width=250)
    _print_paired_tests(console, tmp_path)
    text = console.export_text()
    assert "adam vs gn" in text and "gn 2 of 2" in text and "e-29" not in text and "e+28" not in text
    assert text.count("n/a: 2 seeds (min p 0.5)") == 3  # every pair
    assert "<1e-300" not in text and "Wilcoxon" in text


# --- aggregates over seeds -------------------------------------------------------------------


def numpy_percentile_bootstrap(x, resamples=20000, confidence=0.95, seed=123):
    """The reference: resample the seeds with replacement, median of each resample, the
    percentiles of those medians (NumPy only)."""
    rng = np.random.default_rng(seed)
    medians = np.median(np.asarray(x)[rng.integers(0, len(x), (resamples, len(x)))], axis=1)
    alpha = (1 - confidence) / 2
    with np.errstate(invalid="ignore"):  # medians of +inf: NumPy's interpolation gives NaN there
        return np.percentile(medians, [100 * alpha, 100 * (1 - alpha)]), medians


SEVEN = np.array([0.31, 0.12, 0.55, 0.27, 0.90, 0.18, 0.42])


def test_bootstrap_interval_matches_a_numpy_percentile_bootstrap():
    """7 seeds: the median of a resample is one of the order statistics, and the 2.5 % and
    97.5 % points of its distribution fall well inside the 2nd and 6th (P(median ≤ x(1)) =
    P(Bin(7, 1/7) ≥ 4) = 0.8 %, P(median ≤ x(2)) = 10 %): both bootstraps land on them exactly."""
    low, high = seedstats.bootstrap_interval(SEVEN)
    (ref_low, ref_high), _ = numpy_percentile_bootstrap(SEVEN)
    ordered = np.sort(SEVEN)
    assert (low, high) == (ref_low, ref_high) == (ordered[1], ordered[5])
    # a mean: a continuous bootstrap distribution; the two Monte Carlo estimates agree closely
    mean_low, mean_high = seedstats.bootstrap_interval(SEVEN, statistic=lambda x, axis: np.mean(x, axis=axis))
    rng = np.random.default_rng(7)
    means = SEVEN[rng.integers(0, 7, (20000, 7))].mean(axis=1)
    assert mean_low == pytest.approx(np.percentile(means, 2.5), abs=0.01)
    assert mean_high == pytest.approx(np.percentile(means, 97.5), abs=0.01)
    assert seedstats.bootstrap_interval(SEVEN) == (low, high)  # a fixed generator: the same table every time


def test_bootstrap_interval_with_failures_and_too_few_seeds():
    one_failed = np.append(SEVEN[:6], np.inf)  # the 7th order statistic is a failure
    low, high = seedstats.bootstrap_interval(one_failed)
    assert (low, high) == tuple(np.sort(one_failed)[[1, 5]])  # P(median ≤ x(6)) = 99 %: still finite
    two_failed = np.append(SEVEN[:5], [np.inf, np.inf])
    low, high = seedstats.bootstrap_interval(two_failed)
    _, medians = numpy_percentile_bootstrap(two_failed)
    assert high == math.inf and np.mean(np.isinf(medians)) > 0.025 and low == np.sort(two_failed)[1]
    assert all(math.isnan(v) for v in seedstats.bootstrap_interval([0.1, 0.2]))  # 2 seeds: no interval
    assert seedstats.bootstrap_interval([math.inf] * 3) == (math.inf, math.inf)


def test_summary_counts_a_diverged_seed_as_a_failure():
    s = seedstats.summarize([7.147e-4, math.inf])  # the survivor-bias case of the issue
    assert s["median"] == math.inf and s["mean"] == math.inf and s["failed"] == 1 and math.isnan(s["low"])
    assert seedstats.median_cell(s) == "∞ [n/a: 2 seeds]" and seedstats.mean_cell(s) == "∞ (1 diverged)"
    s = seedstats.summarize([1.0, 2.0, math.inf])
    assert s["median"] == 2.0 and s["mean"] == math.inf and s["high"] == math.inf
    s = seedstats.summarize([1.0, 2.0, 4.0])
    assert (s["median"], s["mean"], s["std"]) == (2.0, pytest.approx(7 / 3), pytest.approx(np.std([1, 2, 4], ddof=1)))
    assert [seedstats.seed_ratio(*p) for p in ((1, 2), (math.inf, 2), (1, math.inf), (math.inf, math.inf),
                                                (0, 0), (1, 0))] == [0.5, math.inf, 0.0, 1.0, 1.0, math.inf]  # fmt: skip


def test_ratios_are_summarised_on_their_logarithms():
    """A ratio and its inverse agree; a failure in a middle seed decides the median instead
    of being averaged with a finite ratio (the demo once printed adam/gn 56.4 from 113 and 0)."""
    assert seedstats.ratio_summary([113.0, 0.0])["median"] == 0.0
    assert seedstats.ratio_summary([1 / 113.0, math.inf])["median"] == math.inf
    assert seedstats.ratio_summary([2.0, 8.0])["median"] == pytest.approx(4.0)
    assert seedstats.ratio_summary([0.5, 0.125])["median"] == pytest.approx(0.25)
    assert math.isnan(seedstats.ratio_summary([0.0, math.inf])["median"])  # one failure each way: undecided
    r = seedstats.ratio_summary([0.5, 0.6, 0.7, 0.8, 2.0, 0.0, 0.9])
    # 7 seeds, one ratio 0 (−∞ in logs): the 2nd and 6th order statistics, as for SEVEN below
    assert (r["median"], r["low"], r["high"], r["n"]) == (pytest.approx(0.7), pytest.approx(0.5), pytest.approx(0.9), 7)


def test_compare_with_one_diverged_seed_never_reports_the_survivor(tmp_path):
    """gn diverged on 1 of 2 seeds and reached 7.147e-04 on the other: its aggregate is the
    failure (∞), not the survivor's value, and its ratio to adam pairs by seed."""
    for seed, (adam, hig) in enumerate([(0.05, 2e-3), (0.04, 1e-3)]):
        write_run(tmp_path, "adam", seed, "finished", np.full(CASES, adam), final=adam)
        write_run(tmp_path, "hig", seed, "finished", np.full(CASES, hig) * np.linspace(0.5, 1.5, CASES), final=hig)
    write_run(tmp_path, "gn", 0, "finished", np.full(CASES, 7.147e-4), final=7.147e-4)
    write_run(tmp_path, "gn", 1, "diverged", np.full(CASES, 1e28))
    collect(tmp_path)
    (tmp_path / "study.json").write_text(json.dumps({"problem": "toy", "methods": ["adam", "gn", "hig"],
                                                     "seeds": [0, 1]}))  # fmt: skip
    result = report(tmp_path)
    rows = {line[0]: dict(zip(result.lines[0], line)) for line in result.lines[1:]}
    gn = rows["gn"]
    assert gn["runs"] == "2 (1 of 2 diverged)"
    assert gn["final test loss, median [95% CI]"] == "∞ [n/a: 2 seeds]"
    assert gn["mean ± std"] == "∞ (1 diverged)"
    assert not any("7.147e-04" in cell for cell in gn.values())
    assert result.final_test_loss("gn") == math.inf and result.final_test_loss("hig") == pytest.approx(1.5e-3)
    geometric = math.sqrt(2e-3 / 0.05 * 1e-3 / 0.04)  # 2 seeds: the median of the log-ratios
    assert rows["hig"]["final / adam"] == f"{geometric:.3g} [n/a: 2 seeds]"
    assert rows["gn"]["final / adam"].startswith("∞")  # its middle seed's failure decides, never averaged away
    assert result.ratio("adam", "hig")["median"] == pytest.approx(1 / geometric)
    assert result.ratio("adam", "gn")["median"] == 0.0
    # the test-case spread: each seed's std over its cases, median over seeds (gn: a failure, ∞)
    spread = case_spread(tmp_path, "loss")
    expected = np.median([np.std(h * np.linspace(0.5, 1.5, CASES), ddof=1) for h in (2e-3, 1e-3)])
    assert (
        spread["hig"] == pytest.approx(expected)
        and spread["adam"] == pytest.approx(0.0, abs=1e-15)
        and spread["gn"] == math.inf
    )
    assert rows["hig"]["test-case spread"] == f"{expected:.1e}"
    assert result.figure is not None and result.figure.exists()


@pytest.mark.parametrize(
    "p, text",
    [
        (0.0, "<1e-300"),
        (1e-320, "<1e-300"),  # subnormal: below what the computation resolves
        (3.2e-5, "3.2e-05"),
        (0.04, "0.04"),
        (0.041, "0.041"),
        (2 / 2**6, "0.031"),
        (0.5, "0.5"),
        (0.9999, "0.9999"),  # just below 1 must not round to "1"
        (1.0, "1.0"),
        (math.nan, "n/a"),
    ],
)
def test_format_p(p, text):
    assert format_p(p) == text


def test_format_p_never_prints_a_bare_zero_or_one():
    for p in np.concatenate([[0.0, 5e-324, 1e-310], np.logspace(-320, 0, 400), 1 - np.logspace(-16, -1, 50)]):
        text = format_p(p)
        assert text not in ("0", "1", "0.0") and (text == "1.0") == (p == 1.0)
        if p >= 1e-300:
            assert float(text) == pytest.approx(p, rel=0.05)

"""Paired statistics between methods: diverged runs stay out of the pairs, p-values print as
numbers that never read as a bare 0 or 1, and a ratio of broken means is not shown.

The study directories here are written file by file in the layout a run leaves behind
(``config.json``, ``summary.json``, ``metrics.csv``, ``test_cases.json``) and gathered by
``study.collect``, so the statistics read exactly what a real study would give them. The
expected numbers come from the test's own arrays and ``scipy.stats.wilcoxon``.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from scipy.stats import wilcoxon

from physgrad.harness.stats import COLUMNS, case_values, format_p, format_tests, paired_tests, seed_means
from physgrad.harness.study import collect

CASES = 20


def write_run(study, method, seed, status, values, metric="rel_error"):
    """One run directory as training leaves it; a diverged run also has test cases (from
    its last finite parameters), which is what must not enter the pairs."""
    run = study / "runs" / f"{method}-seed{seed}-0000"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"problem": "toy", "method": method, "seed": seed}))
    diverged = status == "diverged"
    (run / "summary.json").write_text(json.dumps({
        "status": status, "steps": 10, "epochs": 1.0, "train_seconds": 1.0, "time_per_step": 0.1,
        "final_train_loss": None if diverged else 1.0, "final_test_loss": None if diverged else 1.0,
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


def test_diverged_seed_is_left_out_of_the_pairs(tmp_path):
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
    assert seed_means(tmp_path)["gn"][2] == 2  # gn's mean is over its 2 finished seeds

    (row,) = paired_tests(tmp_path, order=["adam", "gn"])
    x = np.concatenate([reference_arrays(s)[0] for s in (0, 2)])
    y = np.concatenate([reference_arrays(s)[1] for s in (0, 2)])
    assert row["pairs"] == 2 * CASES and row["seeds"] == 2 and row["seeds_a_lower"] == 2
    assert row["p_value"] == pytest.approx(wilcoxon(x, y).pvalue, rel=1e-12)
    assert row["ratio"] == pytest.approx(np.mean(x) / np.mean(y), rel=1e-12)
    assert row["a_lower"] == pytest.approx(np.mean(x < y))
    assert (row["runs_a"], row["diverged_a"], row["runs_b"], row["diverged_b"], row["dropped"]) == (3, 0, 3, 1, 0)

    # The file: original columns first and in their order, floats that parse, no diverged seed.
    with open(tmp_path / "paired_tests.csv") as f:
        header = next(csv.reader(f))
    assert tuple(header[:9]) == ("metric", "method_a", "method_b", "pairs", "a_lower", "seeds", "seeds_a_lower",
                                 "ratio", "p_value")  # fmt: skip
    assert tuple(header) == COLUMNS
    (written,) = read_rows(tmp_path / "paired_tests.csv")
    assert float(written["p_value"]) == pytest.approx(row["p_value"], rel=1e-12)
    assert float(written["ratio"]) == pytest.approx(row["ratio"], rel=1e-12)
    assert int(written["pairs"]) == 2 * CASES and int(written["diverged_b"]) == 1

    head, line = format_tests([row])
    cells = dict(zip(head, line))
    assert cells["diverged"] == "gn 1/3" and cells["seeds lower"] == "2/2" and cells["pairs"] == str(2 * CASES)
    assert cells["mean ratio"] == f"{np.mean(x) / np.mean(y):.3g}"
    assert cells["Wilcoxon p"] == format_p(wilcoxon(x, y).pvalue)


def test_a_pair_with_every_seed_diverged_says_so_instead_of_numbers(tmp_path):
    for seed in (0, 1):
        a, b = reference_arrays(seed)
        write_run(tmp_path, "adam", seed, "finished", a)
        write_run(tmp_path, "gn", seed, "diverged", np.full(CASES, 1e28))
        write_run(tmp_path, "hig", seed, "finished", b)
    collect(tmp_path)
    rows = {(r["method_a"], r["method_b"]): r for r in paired_tests(tmp_path, order=["adam", "gn", "hig"])}
    assert set(rows) == {("adam", "gn"), ("adam", "hig"), ("gn", "hig")}
    for pair in (("adam", "gn"), ("gn", "hig")):
        assert rows[pair]["pairs"] == 0 and math.isnan(rows[pair]["p_value"]) and math.isnan(rows[pair]["ratio"])
    assert rows[("adam", "hig")]["pairs"] == 2 * CASES

    lines = format_tests(list(rows.values()))
    by_pair = {line[0]: dict(zip(lines[0], line)) for line in lines[1:]}
    assert by_pair["adam vs gn"]["mean ratio"] == "n/a (gn diverged 2/2)"
    assert by_pair["adam vs gn"]["Wilcoxon p"] == "n/a (gn diverged 2/2)"
    assert by_pair["gn vs hig"]["diverged"] == "gn 2/2"
    assert by_pair["adam vs hig"]["diverged"] == "-"
    for cells in by_pair.values():
        assert cells["Wilcoxon p"] not in ("0", "1")

    written = {(r["method_a"], r["method_b"]): r for r in read_rows(tmp_path / "paired_tests.csv")}
    assert math.isnan(float(written[("adam", "gn")]["p_value"])) and int(written[("adam", "gn")]["pairs"]) == 0


def test_non_finite_cases_of_finished_runs_are_dropped_and_counted(tmp_path):
    a, b = reference_arrays(0)
    b_broken = b.copy()
    b_broken[[3, 11]] = [np.inf, np.nan]
    write_run(tmp_path, "adam", 0, "finished", a)
    write_run(tmp_path, "gn", 0, "finished", b_broken)
    collect(tmp_path)
    (row,) = paired_tests(tmp_path, order=["adam", "gn"])
    keep = np.isfinite(b_broken)
    assert row["pairs"] == CASES - 2 and row["dropped"] == 2
    assert row["p_value"] == pytest.approx(wilcoxon(a[keep], b[keep]).pvalue, rel=1e-12)
    assert row["ratio"] == pytest.approx(np.mean(a[keep]) / np.mean(b[keep]), rel=1e-12)
    _, line = format_tests([row])
    assert f"{CASES - 2} (2 non-finite dropped)" in line


def test_a_zero_mean_gives_no_ratio(tmp_path):
    a, _ = reference_arrays(0)
    write_run(tmp_path, "adam", 0, "finished", a)
    write_run(tmp_path, "exact", 0, "finished", np.zeros(CASES))
    collect(tmp_path)
    (row,) = paired_tests(tmp_path, order=["adam", "exact"])
    assert math.isnan(row["ratio"]) and row["pairs"] == CASES
    head, line = format_tests([row])
    assert dict(zip(head, line))["mean ratio"] == "n/a"


def test_an_underflowing_p_value_prints_as_a_bound(tmp_path):
    """Thousands of pairs with a clear shift: scipy's normal approximation underflows to
    0, which once printed as a bare ``Wilcoxon p 0``."""
    rng = np.random.default_rng(1)
    a = rng.uniform(1.0, 2.0, 2000)
    b = a + rng.uniform(0.5, 1.0, 2000)
    write_run(tmp_path, "adam", 0, "finished", a)
    write_run(tmp_path, "gn", 0, "finished", b)
    collect(tmp_path)
    (row,) = paired_tests(tmp_path, order=["adam", "gn"])
    assert row["p_value"] == pytest.approx(wilcoxon(a, b).pvalue, abs=1e-300) and row["p_value"] < 1e-300
    head, line = format_tests([row])
    assert dict(zip(head, line))["Wilcoxon p"] == "<1e-300"


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
    assert row["pairs"] == CASES and row["diverged_b"] == 1 and row["p_value"] == pytest.approx(wilcoxon(
        np.arange(1.0, CASES + 1), np.arange(2.0, CASES + 2)).pvalue)  # fmt: skip


def test_the_printed_table_follows(tmp_path):
    """The command line's table (compare, report, demo) is built from format_tests."""
    from rich.console import Console

    from physgrad.harness.cli import _print_paired_tests

    for seed in (0, 1):
        a, _ = reference_arrays(seed)
        write_run(tmp_path, "adam", seed, "finished", a)
        write_run(tmp_path, "gn", seed, "diverged", np.full(CASES, 1e28))
    collect(tmp_path)
    console = Console(record=True, width=200)
    _print_paired_tests(console, tmp_path)
    text = console.export_text()
    assert "adam vs gn" in text and "n/a (gn diverged 2/2)" in text and "e-29" not in text


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

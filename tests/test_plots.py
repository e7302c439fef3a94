"""Figures never lose a study: NaN, infinite and overflowing losses are clipped to the axis
and marked; the tables come first; a figure that fails is one warning line (issue 29)."""

import csv
import json
import math
import warnings

import numpy as np
import pytest

from physgrad.harness import plots, study
from physgrad.harness.cli import main

# A diverging run's test loss: finite values growing to the largest floats, then inf and NaN.
DIVERGING = [90.0, 8.1e25, 8.1e49, 8.1e97, 8.1e289, 1e308, math.inf, math.nan]
HEALTHY = [90.0, 10.0, 1.0, 0.1, 0.01, 1e-3]


def metric_rows(method, values, seed=0):
    return [{"problem": "toy2d", "method": method, "seed": str(seed), "step": str(i), "wall_time": str(0.01 * i),
             "split": "test", "metric": "loss", "value": repr(v)} for i, v in enumerate(values)]  # fmt: skip


def write_study(out, diverging=DIVERGING):
    """A study directory as ``compare`` leaves it: one finished and one diverged method."""
    out.mkdir(parents=True)
    results = metric_rows("newton", HEALTHY) + metric_rows("gn", diverging)
    results += metric_rows("gn", diverging[:3], seed=1)
    with (out / "results.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(results[0]))
        writer.writeheader()
        writer.writerows(results)
    summary: list[dict[str, object]] = [
        {"problem": "toy2d", "method": "newton", "seed": 0, "status": "finished", "steps": 5, "epochs": 5,
         "train_seconds": 0.05, "time_per_step": 0.01, "final_train_loss": 1e-3, "final_test_loss": 1e-3,
         "best_test_loss": 1e-3, "run_dir": "runs/a"},
        {"problem": "toy2d", "method": "gn", "seed": 0, "status": "diverged", "steps": 6, "epochs": 6,
         "train_seconds": 0.06, "time_per_step": 0.01, "final_train_loss": "inf", "final_test_loss": "inf",
         "best_test_loss": 90.0, "diverged_step": 6, "last_finite_loss": 1e308, "run_dir": "runs/b"},
    ]  # fmt: skip
    with (out / "summary.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[str(c) for c in study.SUMMARY_COLUMNS], extrasaction="ignore")
        writer.writeheader()
        writer.writerows(summary)
    (out / "study.json").write_text(json.dumps({"problem": "toy2d", "methods": ["gn", "newton"], "seeds": [0]}))


def test_log_range_and_marks_keep_the_axis_finite():
    lower, upper = plots.log_range([np.array(HEALTHY), np.array(DIVERGING)])
    assert lower == pytest.approx(1e-3)
    assert upper == pytest.approx(1e5)  # three decades above the highest start (90 -> 1e2)
    t, v, (mt, mv) = plots.clip_marks(np.arange(len(DIVERGING)), np.array(DIVERGING), lower, upper)
    assert np.isfinite(v).all() and v.max() == upper
    assert list(mt) == [1, 2, 3, 4, 5, 6, 7]  # every off-scale, infinite or NaN point is marked
    assert (mv == upper).all()
    assert plots.log_range([np.array([math.nan, math.inf])]) == (1e-3, 1.0)  # nothing finite: a default range


@pytest.mark.parametrize("huge", [1e308, math.inf, math.nan])
def test_loss_vs_time_draws_overflowing_losses(tmp_path, huge):
    rows = metric_rows("newton", HEALTHY) + metric_rows("gn", [90.0, 1e200, 8.1e289, huge])
    rows += metric_rows("gn", [90.0, 1e100, huge], seed=1)
    path = plots.loss_vs_time(rows, tmp_path / "loss.png", order=["gn", "newton"], notes={"gn": "2/2 diverged"})
    assert path.exists() and path.stat().st_size > 1000


def test_grid_panels_draw_overflowing_losses(tmp_path):
    def cell_rows(values):
        return [{**r, "epoch": float(r["step"])} for r in metric_rows("gn", values)]

    cells = [({"clip": "value"}, cell_rows(DIVERGING)), ({"clip": "norm"}, cell_rows(HEALTHY + [0.0]))]
    path = plots.grid_panels(cells, tmp_path / "grid.png", panel="clip", methods=["gn"], smooth=3)
    assert path.exists() and path.stat().st_size > 1000


def test_report_of_a_study_with_a_diverged_huge_loss(tmp_path):
    write_study(tmp_path / "s")
    result = study.report(tmp_path / "s")
    assert result.figure is not None and result.figure.exists()
    assert [line[0] for line in result.lines[1:]] == ["gn", "newton"]


def test_a_failing_figure_is_one_warning_and_the_table_stands(tmp_path, monkeypatch, capsys):
    write_study(tmp_path / "s")

    def broken(*args, **kwargs):
        raise OverflowError("cannot convert float infinity to integer")

    monkeypatch.setattr(plots, "loss_vs_time", broken)
    with pytest.warns(plots.FigureWarning, match="not drawn .*OverflowError"):
        result = study.report(tmp_path / "s")
    assert result.figure is None and len(result.lines) == 3
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["report", str(tmp_path / "s")]) == 0
    captured = capsys.readouterr()
    assert "newton" in captured.out and "gn" in captured.out  # the table is printed
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("physgrad: warning: figure") and "OverflowError" in lines[0]
    assert "Traceback" not in captured.err


def test_cli_report_prints_the_table_and_draws_the_figure(tmp_path, capsys):
    write_study(tmp_path / "s")
    assert main(["report", str(tmp_path / "s")]) == 0
    captured = capsys.readouterr()
    assert "1 (1 of 1 diverged)" in captured.out and "newton" in captured.out
    assert (tmp_path / "s" / "loss_vs_time.png").exists()
    assert "warning" not in captured.err


def test_the_median_over_seeds_never_averages_over_a_divergence():
    """Two seeds, one diverged at t = 0.5: from there on the median is the top of the axis
    (the table's median is +∞ too), not a mean of the survivor and the failure."""
    t = np.linspace(0.0, 1.0, 11)
    survivor = (t, 10.0 ** -(1 + 2 * t), False)
    diverged = (t[:6], 10.0 ** -(1 + 2 * t[:6]) * 1.5, True)
    grid, median = plots.seed_median([survivor, diverged], upper=100.0)
    late = grid > 0.5
    assert np.allclose(median[late], 100.0) and np.all(median[~late] < 1.0)
    grid, median = plots.seed_median([survivor, survivor, diverged], upper=100.0)  # 1 of 3: the survivors' median
    assert np.all(median < 1.0)


def test_each_seed_is_drawn_and_a_divergence_marked(tmp_path):
    rows = metric_rows("hig", HEALTHY) + metric_rows("hig", HEALTHY[:3], seed=1) + metric_rows("adam", HEALTHY)
    path = plots.loss_vs_time(rows, tmp_path / "seeds.png", order=["adam", "hig"], notes={"hig": "1 of 2 diverged"},
                              diverged={"hig": {"1"}})  # fmt: skip
    assert path.exists() and path.stat().st_size > 1000

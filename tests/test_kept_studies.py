"""The committed short-study files (docs/reproductions/data/short) and the script that keeps
them: a clone redraws the reproduction reports from them alone."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from physgrad.harness.calibration import read
from physgrad.harness.study import load_studies

ROOT = Path(__file__).resolve().parent.parent
KEPT = ROOT / "docs" / "reproductions" / "data" / "short"


def _keep_module():
    spec = importlib.util.spec_from_file_location("keep_studies", ROOT / "docs/reproductions/keep_studies.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _write(path: Path, text: str = "x"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_keep_copies_study_files_and_leaves_checkpoints_and_unfinished_studies(tmp_path):
    src, dst = tmp_path / "studies", tmp_path / "kept"
    done = src / "sweep" / "cell_a"
    for name in ("study.json", "summary.csv", "results.csv", "calibration.json"):
        _write(done / name)
    _write(done / "runs" / "adam-seed0" / "config.json")
    _write(done / "runs" / "adam-seed0" / "checkpoint" / "state.eqx")
    _write(src / "sweep" / "grid.json")
    _write(src / "running" / "study.json")  # no summary.csv: not finished

    keep = _keep_module().keep
    copied = {p.relative_to(dst).as_posix() for p in keep(src, dst)}
    assert copied == {
        "sweep/cell_a/study.json", "sweep/cell_a/summary.csv", "sweep/cell_a/results.csv",
        "sweep/cell_a/calibration.json", "sweep/grid.json",
    }  # fmt: skip
    assert not (dst / "running").exists()

    with_runs = {p.relative_to(tmp_path / "kept2").as_posix() for p in keep(src, tmp_path / "kept2", runs=True)}
    assert "sweep/cell_a/runs/adam-seed0/config.json" in with_runs
    assert not any("checkpoint" in p for p in with_runs)


def test_keep_gzips_the_curves_and_the_study_reads_them_back(tmp_path):
    """--gzip keeps results.csv as results.csv.gz, byte-identical when kept again; the study
    functions (read_csv, load_studies, report) read the packed copy where the plain one is gone."""
    import csv

    from physgrad.harness.study import read_csv, report

    src, dst = tmp_path / "studies", tmp_path / "kept"
    study = src / "cell"
    rows = [{"problem": "toy2d", "method": "adam", "seed": str(s), "step": str(t), "wall_time": str(0.1 * t),
             "split": split, "metric": "loss", "value": str(1.0 / (1 + t + s))}
            for s in (0, 1) for t in range(0, 30, 10) for split in ("train", "test")]  # fmt: skip
    study.mkdir(parents=True)
    with (study / "results.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _write(study / "study.json", json.dumps({"problem": "toy2d", "methods": ["adam"], "seeds": [0, 1]}))
    summary = [{"problem": "toy2d", "method": "adam", "seed": str(s), "status": "finished", "steps": "20",
                "final_train_loss": "0.05", "final_test_loss": "0.05", "best_test_loss": "0.04",
                "time_per_step": "0.01", "train_seconds": "0.2", "run_dir": f"runs/{s}"} for s in (0, 1)]  # fmt: skip
    with (study / "summary.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(summary[0]))
        writer.writeheader()
        writer.writerows(summary)
    keep = _keep_module().keep
    _write(dst / "cell" / "results.csv")  # a plain copy kept earlier goes: one copy of the curves
    copied = {p.relative_to(dst).as_posix() for p in keep(src, dst, packed=True)}
    assert "cell/results.csv.gz" in copied and not (dst / "cell" / "results.csv").exists()
    first = (dst / "cell" / "results.csv.gz").read_bytes()
    keep(src, dst, packed=True)
    assert (dst / "cell" / "results.csv.gz").read_bytes() == first
    assert read_csv(dst / "cell" / "results.csv") == read_csv(study / "results.csv") == rows
    assert load_studies(dst, [("cell", "")])[1] == rows
    report(dst / "cell")  # finds its curves packed (it refused: "results.csv is missing")
    # re-collecting a kept study (a report script does) rewrites its curves packed, not beside them
    from physgrad.harness.study import RESULT_COLUMNS, write_csv

    _write(dst / "cell" / "results.csv", "stale")  # a plain copy beside the packed one goes
    write_csv(dst / "cell" / "results.csv", RESULT_COLUMNS, rows)
    assert not (dst / "cell" / "results.csv").exists()
    assert read_csv(dst / "cell" / "results.csv") == [{k: r.get(k, "") for k in RESULT_COLUMNS} for r in rows]


def _kept_studies():
    return sorted(p.parent for p in KEPT.rglob("study.json") if "runs" not in p.relative_to(KEPT).parts)


@pytest.mark.parametrize("study", _kept_studies(), ids=lambda p: p.relative_to(KEPT).as_posix())
def test_each_kept_study_is_complete(study):
    """Every run the study planned is in its summary, with a curve in results.csv and a time
    per step in its calibration: the report draws its table and figure from these alone."""
    record = json.loads((study / "study.json").read_text())
    rows, results, order = load_studies(study.parent, [(study.name, "")])
    planned = {(m, str(s)) for m in record["methods"] for s in record["seeds"]}
    assert {(r["method"], r["seed"]) for r in rows} == planned
    assert all(r["status"] in ("finished", "diverged") for r in rows)
    curves = {(r["method"], r["seed"]) for r in results if r["split"] == "test"}
    assert curves == planned
    if "seconds" in record["budget"]:  # a calibrated budget: each method's step (each stage's) was timed
        calibration = read(study)
        assert calibration is not None and all(calibration.has(m) for m in order)


def test_keep_merges_the_bench_records_of_lanes_into_one(tmp_path):
    """A bench split over lanes (one directory each) is gathered into one: its bench.json
    lists every lane's problems, verdicts, budgets and per-problem settings; a lane of a
    different bench is refused."""
    keep = _keep_module().keep

    def lane(name, problem, **extra):
        info = {"problems": [problem], "methods": ["adam", "hig"], "seeds": [0, 1], "budget": {"seconds": 300.0},
                "profile": "standard", "settings": {"eval_seconds": "10", **extra.pop("settings", {})},
                "budgets": extra.pop("budgets", {}),
                "verdicts": {problem: [{"method": "adam", "status": "applicable", "reason": ""}]}, **extra}  # fmt: skip
        _write(tmp_path / name / "bench.json", json.dumps(info))
        return tmp_path / name

    dst = tmp_path / "kept"
    keep(lane("a", "toy2d", budgets={"toy2d": {"seconds": 5.0}}, settings={"toy2d.eval_seconds": "0.1"}), dst)
    keep(lane("b", "oscillators"), dst)
    merged = json.loads((dst / "bench.json").read_text())
    assert merged["problems"] == ["toy2d", "oscillators"]
    assert set(merged["verdicts"]) == {"toy2d", "oscillators"}
    assert merged["budgets"] == {"toy2d": {"seconds": 5.0}}
    assert merged["settings"] == {"eval_seconds": "10", "toy2d.eval_seconds": "0.1"}
    with pytest.raises(SystemExit, match="seeds"):
        keep(lane("c", "sine", seeds=[0]), dst)
    with pytest.raises(SystemExit, match="setting eval_seconds"):
        keep(lane("d", "sine", settings={"eval_seconds": "1"}), dst)


BENCHES = ROOT / "docs" / "benchmark"


# `physgrad report` over the whole committed bench (10 s of CPU); the fast tier tests the bench
# tables and the leaderboard on small studies (test_bench.py).
@pytest.mark.slow
@pytest.mark.parametrize("kept", ["dense"])
def test_a_kept_bench_is_redrawn_from_its_files(kept, tmp_path, capsys):
    """The committed bench (its problems kept without their runs, or with their small files)
    redraws its tables and leaderboard with `physgrad report` from a clone: the same ranks and
    final losses as the committed tables, every kept problem ranked."""
    import csv
    import shutil

    from physgrad.harness.cli import main

    copy = shutil.copytree(BENCHES / kept, tmp_path / kept)
    assert main(["report", str(copy)]) == 0
    assert "leaderboard" in capsys.readouterr().out
    info = json.loads((copy / "bench.json").read_text())
    for problem in info["problems"]:
        if not (copy / problem / "summary.csv").exists():
            continue  # a lane still running: its table says pending
        with (copy / problem / "bench_table.csv").open() as f:
            table = {r["method"]: r for r in csv.DictReader(f)}
        with (BENCHES / kept / problem / "bench_table.csv").open() as f:
            committed = {r["method"]: r for r in csv.DictReader(f)}
        assert {m: (r["rank"], r["final_test_loss_median"]) for m, r in table.items()} == {
            m: (r["rank"], r["final_test_loss_median"]) for m, r in committed.items()}, problem  # fmt: skip
        assert any(r["rank"] == "1" for r in table.values()), problem


def test_prune_removes_only_the_checkpoints_of_final_runs(tmp_path):
    """long/prune.py: a finished or diverged run's checkpoint goes, a run in progress (no
    summary, or one without its final losses) keeps its own, and nothing else is touched."""
    spec = importlib.util.spec_from_file_location("prune", ROOT / "docs/reproductions/long/prune.py")
    prune = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(prune)
    runs = {
        "finished": {"status": "finished", "final_test_loss": 0.1},
        "diverged": {"status": "diverged"},
        "running": {"status": "finished"},  # an older summary without its final losses
        "fresh": None,  # no summary yet
    }
    for name, summary in runs.items():
        _write(tmp_path / "study" / "adam" / "runs" / name / "checkpoint" / "state.eqx")
        _write(tmp_path / "study" / "adam" / "runs" / name / "metrics.csv")
        if summary is not None:
            _write(tmp_path / "study" / "adam" / "runs" / name / "summary.json", json.dumps(summary))
    found = prune.final_checkpoints(tmp_path)
    assert [p.parent.name for p in found] == ["diverged", "finished"]
    # --pack: a final run's metrics.csv gzipped; physgrad reads the packed copy back
    from physgrad.engine import read_metrics

    run = tmp_path / "study" / "adam" / "runs" / "finished"
    (run / "metrics.csv").write_text("step,wall_time,split,metric,value\n0,0.0,test,loss,2.5\n10,1.5,test,loss,0.5\n")
    before = read_metrics(run / "metrics.csv")
    (run / "test_cases.json").write_text('{"loss": [0.25, 0.75]}')
    prune.pack_run(run)
    assert (run / "metrics.csv.gz").exists() and not (run / "metrics.csv").exists()
    assert (run / "test_cases.json.gz").exists() and not (run / "test_cases.json").exists()
    assert read_metrics(run / "metrics.csv") == before
    from physgrad.engine.result import history_from_metrics  # a finished run's result reads it

    assert history_from_metrics(run / "metrics.csv")["step"].tolist() == [0, 10]
    # the paired statistics read the packed test cases
    from physgrad.harness.stats import case_values

    (tmp_path / "study" / "adam" / "summary.csv").write_text(
        "method,seed,status,run_dir\nadam,0,finished,runs/finished\n"
    )
    metric, values = case_values(tmp_path / "study" / "adam")
    assert metric == "loss" and values["adam"][0].tolist() == [0.25, 0.75]
    assert [r["value"] for r in before] == [2.5, 0.5]
    # a finished study's results.csv gzipped; its reader and its writer take the packed copy
    from physgrad.harness.study.tables import read_csv, write_csv

    table = tmp_path / "study" / "adam" / "results.csv"
    table.write_text("method,seed,value\nadam,0,0.5\n")
    prune.pack_table(table)
    assert not table.exists() and read_csv(table) == [{"method": "adam", "seed": "0", "value": "0.5"}]
    write_csv(table, ["method", "seed", "value"], [{"method": "adam", "seed": 1, "value": 0.25}])
    assert not table.exists() and read_csv(table)[0]["seed"] == "1"


def test_pack_finished_finds_the_tuned_problems_whose_test_study_is_complete(tmp_path):
    """prune.py --pack-finished: a tuned problem is done when final/summary.csv has one row per
    test run and every test run is final; one with a run under way, or no test study yet, is not."""
    spec = importlib.util.spec_from_file_location("prune", ROOT / "docs/reproductions/long/prune.py")
    prune = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(prune)
    final = {"status": "finished", "final_test_loss": 0.1}
    for problem, states in {"done": [final, final], "running": [final, {"status": "finished"}], "trials": []}.items():
        _write(tmp_path / "lane" / problem / "tune.json", "{}")
        for i, state in enumerate(states):
            _write(tmp_path / "lane" / problem / "final" / "runs" / f"adam-seed{i}" / "summary.json", json.dumps(state))
        if states:
            _write(tmp_path / "lane" / problem / "final" / "summary.csv", "method,seed\n" + "adam,0\n" * len(states))
    assert [p.name for p in prune.finished_tunes(tmp_path)] == ["done"]


def _long_report(monkeypatch):
    spec = importlib.util.spec_from_file_location("long_report", ROOT / "docs/reproductions/long/report.py")
    report = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, report)  # its dataclasses look their module up
    spec.loader.exec_module(report)
    return report


def test_long_report_refuses_an_unknown_study_in_one_line(capsys, monkeypatch):
    """long/report.py with a name that is no kept study (a typo, an option it does not have)
    answers one line listing the studies and exits 2, instead of drawing an empty figure."""
    report = _long_report(monkeypatch)
    for bad in ("ks_corection_2ep", "--all"):
        with pytest.raises(SystemExit) as exit_:
            report.main([bad])
        assert exit_.value.code == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and repr(bad) in err and "ks_correction_2ep" in err
    report.main(["ks_correction_2ep", "--help"])  # the usage, wherever -h stands; nothing drawn
    assert "report.py [STUDY ...]" in capsys.readouterr().out


def test_long_report_tables_a_top_level_compare_output_per_method(tmp_path, monkeypatch):
    """A study kept as one compare output (its runs/ at the top, as the GPU runs) gets one row
    per method, and a method that also has its own directory keeps both rows apart; each
    row gives every seed's final value, a diverged seed by its status."""
    report = _long_report(monkeypatch)

    def run(where, method, seed, losses, status="finished"):
        d = where / "runs" / f"{method}-seed{seed}-x"
        d.mkdir(parents=True)
        rows = "".join(f"{10 * i},{i}.0,test,loss,{v}\n" for i, v in enumerate(losses))
        (d / "metrics.csv").write_text("step,wall_time,split,metric,value\n" + rows)
        (d / "config.json").write_text(json.dumps({"seed": seed, "method": method, "budget": {"steps": 10}}))
        (d / "summary.json").write_text(json.dumps({"status": status, "steps": 10, "diverged_step": None}))

    study = tmp_path / "mixed"
    run(study, "adam", 0, [2.0, 0.5])
    run(study, "adam", 1, [2.0, 1.5])
    run(study, "hig", 0, [2.0, 0.25])
    run(study, "hig", 1, [2.0, float("nan")], status="diverged")
    run(study / "hig", "hig", 2, [2.0, 0.125])
    lines, data = report.table(study, report.calibration())
    rows = {line.split(" | ")[0].removeprefix("| "): line for line in lines[2:]}
    assert set(rows) == {"adam", "hig", "hig (top level)"}
    assert "0: 0.5 / 1: 1.5" in rows["adam"] and "2 finished, 0 diverged" in rows["adam"]
    assert "0: 0.25 / 1: diverged" in rows["hig (top level)"] and "2: 0.125" in rows["hig"]


@pytest.mark.parametrize("task", ["cartpole", "guidance", "quantum", "cartpole_long", "quantum_long"])
def test_stable_bptt_cells_cover_the_sweep_grid(task):
    """A lent machine runs one job per (cell, method) from `stable_bptt_runs.sh cells`; the
    whole-grid sweep must then find every run finished, so the jobs must be exactly its
    cells x methods, at its epochs."""
    import itertools
    import subprocess

    script = ROOT / "docs/reproductions/stable_bptt_runs.sh"
    env = {"PATH": "/usr/bin:/bin", "PHYSGRAD": "echo"}
    sweep = subprocess.run(["bash", script, task], env=env, capture_output=True, text=True, check=True).stdout.split()
    sets = [sweep[i + 1] for i, word in enumerate(sweep) if word == "--set"]
    methods = sweep[sweep.index("--methods") + 1].split(",")
    epochs = sweep[sweep.index("--epochs") + 1]
    axes = [(s.split("=")[0], [v for v in s.split("=")[1].split(",") if v]) for s in sets]
    want = {
        (m, f"{axes[0][0]}={a},", f"{axes[1][0]}={b},")
        for m, a, b in itertools.product(methods, axes[0][1], axes[1][1])
    }
    lines = subprocess.run(
        ["bash", script, "cells", task], env=env, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    jobs = [line.split() for line in lines]
    assert {(j[4], j[5], j[6]) for j in jobs} == want and len(jobs) == len(want)
    assert {(j[1], j[3]) for j in jobs} == {(sweep[1], epochs)}
    bad = subprocess.run(["bash", script, "cells", "nope"], env=env, capture_output=True, text=True)
    assert bad.returncode == 2 and "valid: cartpole" in bad.stderr

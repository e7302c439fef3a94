"""The command line and the run/study files, with tiny budgets."""

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest

import physgrad
from physgrad import Budget
from physgrad.engine.progress import NoProgressMeter
from physgrad.harness.cli import main
from physgrad.harness.config import make_config
from physgrad.harness.registry import METHODS
from physgrad.harness.train import train
from test_validation import module_entry

RUN_FILES = ("config.json", "metrics.csv", "env.json", "summary.json", "params.eqx", "checkpoint/state.eqx")


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def params_of(run_dir):
    net = physgrad.load_network(run_dir)
    return np.concatenate([np.ravel(np.asarray(x)) for x in (net.layers[0].weight, net.layers[1].weight)])


def test_list(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for name in (
        "oscillators",
        "hig_toy",
        "adam",
        "sgd",
        "rmsprop",
        "adagrad",
        "adadelta",
        "gn",
        "hig",
        "lm",
        "optax:lion",
        "optax.contrib:muon",
    ):
        assert name in out


def test_readme_method_table_names_every_registered_method():
    """Each registered method has a row in the README's method table (khig once had none)."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    cells = re.findall(r"^\| ((?:`[^`]+`(?:, )?)+) \|", readme, flags=re.M)
    listed = {name for cell in cells for name in re.findall(r"`([^`]+)`", cell)}
    assert set(METHODS) - listed == set()


def test_train_writes_every_documented_file(tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        main(["train", "hig_toy", "--method", "hig", "--steps", "6", "--set", "eval_every=2", "--out", str(out)]) == 0
    )
    for name in RUN_FILES:
        assert (out / name).exists(), name
    metrics = rows(out / "metrics.csv")
    assert list(metrics[0]) == ["step", "wall_time", "split", "metric", "value"]
    steps = sorted({int(r["step"]) for r in metrics if r["metric"] == "loss"})
    assert steps == [0, 2, 4, 6]
    assert {r["split"] for r in metrics} == {"train", "test"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["steps"] == 6
    assert summary["final_test_loss"] == pytest.approx(
        float([r for r in metrics if r["step"] == "6" and r["split"] == "test" and r["metric"] == "loss"][0]["value"])
    )
    config = json.loads((out / "config.json").read_text())
    assert config["phases"] == [
        {
            "method": "hig",
            "hyperparameters": {"lr": 1.0, "truncation": 1e-6, "route": "auto", "blocks": 8, "lanczos_steps": 64},
            "batch_size": 256,
            "steps": None,
        }
    ]
    assert config["budget"] == {"steps": 6}
    assert json.loads((out / "env.json").read_text())["versions"]["jax"]
    # an existing run directory is not overwritten silently
    assert main(["train", "hig_toy", "--method", "hig", "--steps", "6", "--out", str(out)]) == 2
    assert "--resume" in capsys.readouterr().err


class InterruptAt(NoProgressMeter):
    def __init__(self, step):
        self.at = step

    def update(self, *, step, **kwargs):
        if step >= self.at:  # the first update at or after the step (fit updates once per chunk of steps)
            raise KeyboardInterrupt


def test_resume_after_interrupt_matches_uninterrupted_run(tmp_path):
    config = make_config("hig_toy", "adam", budget=Budget(steps=12), settings={"eval_every": 4, "batch_size": 64})
    whole = train(config, tmp_path / "whole")
    with pytest.raises(KeyboardInterrupt):
        train(config, tmp_path / "cut", progress=InterruptAt(6))
    assert json.loads((tmp_path / "cut" / "summary.json").read_text())["status"] == "interrupted"
    resumed = train(config, tmp_path / "cut", resume=True)
    assert resumed["steps"] == whole["steps"] == 12
    np.testing.assert_array_equal(params_of(tmp_path / "cut"), params_of(tmp_path / "whole"))
    assert resumed["final_test_loss"] == whole["final_test_loss"]
    # metrics: no duplicated rows across the interruption
    steps = [
        int(r["step"]) for r in rows(tmp_path / "cut" / "metrics.csv") if r["split"] == "test" and r["metric"] == "loss"
    ]
    assert steps == [0, 4, 8, 12]


def test_resume_extends_a_finished_run_from_the_cli(tmp_path):
    out = str(tmp_path / "run")
    base = ["train", "hig_toy", "--method", "adam", "--out", out, "--set", "batch_size=64"]
    assert main([*base, "--steps", "5"]) == 0
    assert main([*base, "--steps", "9", "--resume"]) == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["steps"] == 9 and summary["budget"] == {"steps": 9}


def test_compare_report_and_skip(tmp_path, capsys):
    out = tmp_path / "study"
    argv = ["compare", "hig_toy", "--methods", "adam,hig", "--seeds", "2", "--steps", "4", "--out", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "final test loss" in printed and "final / adam" in printed
    for name in ("results.csv", "summary.csv", "loss_vs_time.png", "study.json"):
        assert (out / name).exists(), name
    results = rows(out / "results.csv")
    assert list(results[0])[:3] == ["problem", "method", "seed"]
    assert {(r["method"], r["seed"]) for r in results} == {("adam", "0"), ("adam", "1"), ("hig", "0"), ("hig", "1")}
    summary = rows(out / "summary.csv")
    assert len(summary) == 4 and {r["status"] for r in summary} == {"finished"}
    assert main(argv) == 0
    assert capsys.readouterr().out.count("done already") == 4
    (out / "loss_vs_time.png").unlink()
    assert main(["report", str(out)]) == 0
    assert (out / "loss_vs_time.png").exists()
    assert "hig" in capsys.readouterr().out


def test_diverged_run_is_recorded_and_the_study_goes_on(tmp_path, capsys):
    out = tmp_path / "study"
    argv = ["compare", "hig_toy", "--methods", "sgd,adam", "--steps", "20", "--out", str(out),
            "--set", "sgd.lr=1e12", "--set", "batch_size=64"]  # fmt: skip
    assert main(argv) == 0
    summary = {r["method"]: r for r in rows(out / "summary.csv")}
    assert summary["sgd"]["status"] == "diverged"
    assert int(summary["sgd"]["diverged_step"]) >= 1
    assert np.isfinite(float(summary["sgd"]["last_finite_loss"]))
    assert summary["adam"]["status"] == "finished"
    assert "diverged" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv,message",
    [
        (
            ["train", "nope", "--method", "adam"],
            "unknown problem 'nope'; valid choices: advection_1d, cartpole, exp_inverse, guidance, heat, hig_toy, kolmogorov, ks, linear_oscillators, navier_stokes, oscillators, poisson, poisson_hig, quantum_control, quantum_dipole, sine, toy2d",
        ),
        (
            ["train", "sine", "--method", "sip", "--set", "solver=magic", "--steps", "1"],
            "unknown inverse solver 'magic'; valid choices: auto, analytic",
        ),
        (
            ["train", "sine", "--method", "sip", "--set", "solver=analytic", "--steps", "1"],
            "sip on sine: this problem has no analytic inverse; valid choices: gauss_newton",
        ),
        (
            ["train", "quantum_dipole", "--method", "sip", "--steps", "1"],
            "sip on quantum_dipole: sip needs a problem with network_output, simulate and a y-space target",
        ),
        (
            ["train", "sine", "--method", "sip", "--set", "proxy=l3", "--steps", "1"],
            "unknown proxy 'l3'; valid choices: l2, l1",
        ),
        (["train", "hig_toy", "--method", "nope"], "unknown method 'nope'; valid choices:"),
        (
            ["train", "hig_toy", "--method", "adam", "--set", "nope=1"],
            "unknown setting 'nope' for hig_toy/adam; valid choices:",
        ),
        (["train", "hig_toy", "--method", "adam", "--set", "lr=fast"], "setting 'lr' expects a number, got 'fast'"),
        (
            ["train", "hig_toy", "--method", "hig", "--set", "route=qr", "--steps", "1"],
            "unknown route 'qr'; valid choices",
        ),
        (
            ["train", "hig_toy", "--method", "adam", "--set", "batch_size=1e3"],
            "setting 'batch_size' expects an integer",
        ),
        (["train", "hig_toy", "--method", "adam", "--set", "shuffle=maybe"], "setting 'shuffle' expects true or false"),
        (
            ["train", "hig_toy", "--method", "adam", "--set", "batch_size=4096", "--steps", "1"],
            "batch_size 4096 exceeds the 1024 training samples",
        ),
        (["compare", "nope"], "unknown problem 'nope'"),
        (["compare", "hig_toy", "--methods", "adam,nope"], "unknown method 'nope'"),
        (["compare", "hig_toy", "--set", "nope=1"], "unknown setting 'nope' for hig_toy; valid choices:"),
        (["compare", "hig_toy", "--methods", "adam", "--set", "hig.lr=1"], "unknown method in a scoped setting 'hig'"),
        (["train", "hig_toy", "--method", "adam", "--steps", "1", "--seconds", "2"], "only one of"),
        (["report", "/nonexistent"], "is not a study directory"),
        (["frobnicate"], "invalid choice"),
    ],
)
def test_bad_input_is_one_line_exit_2(argv, message, capsys, tmp_path):
    assert main([*argv, *(["--out", str(tmp_path / "x")] if argv[0] in ("train", "compare") else [])]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_console_script_and_module_entry_points():
    # both commands through physgrad/__main__.py in one fresh interpreter (test_validation.module_entry,
    # as ``python -m physgrad`` runs it; test_packaging starts ``python -m physgrad --version`` itself)
    (listed, out, _), (bad, _, err) = module_entry([["list"], ["train", "nope", "--method", "hig"]])
    assert listed == 0 and "oscillators" in out
    assert bad == 2 and err.strip().count("\n") == 0 and "valid choices" in err


def test_rich_progress_meter_runs_through_a_training_run(tmp_path):
    from physgrad.engine.progress import RichProgressMeter

    meter = RichProgressMeter(refresh_seconds=0.0)
    config = make_config("hig_toy", "adam", budget=Budget(epochs=2), settings={"batch_size": 256})
    summary = train(config, tmp_path / "run", progress=meter)
    assert summary["steps"] == 8 and meter._progress is None  # closed


@pytest.mark.slow
def test_demo_runs_and_prints_its_settings_and_ratio(tmp_path, capsys):
    assert main(["demo", "--seconds", "0.3", "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "batch 32" in out and "hig.batch_size" in out
    assert "below Adam's at equal calibrated time" in out
    assert (tmp_path / "demo" / "loss_vs_time.png").exists()

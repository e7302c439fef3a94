"""A short ``physgrad train`` from the command line and the test losses it recorded: the
end-to-end check that several method tests share (a method trains a problem from the CLI)."""

from __future__ import annotations

from pathlib import Path

from physgrad.engine import read_metrics
from physgrad.harness.cli import main


def cli_test_losses(out: Path, problem: str, method: str, steps: int, settings: dict[str, str]) -> list[float]:
    """Run ``physgrad train PROBLEM --method METHOD --steps STEPS --out OUT --set K=V …``
    (asserting it exits 0) and return the test losses ``OUT/metrics.csv`` recorded, in order."""
    argv = ["train", problem, "--method", method, "--steps", str(steps), "--out", str(out)]
    assert main(argv + [f"--set={k}={v}" for k, v in settings.items()]) == 0
    rows = read_metrics(out / "metrics.csv")
    return [r["value"] for r in rows if r["split"] == "test" and r["metric"] == "loss"]

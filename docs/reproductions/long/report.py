"""Tables and figures of the long studies (docs/reproductions/long/studies.sh), from the
committed run directories alone.

Each study has one directory per method (its own step budget: the paper's wall-clock budget
divided by the method's time per step measured alone, calibration.csv). A curve is drawn
against the calibrated time axis t = step × (seconds per step measured alone) and, in a
second panel, against the run's raw training wall-clock (load-dependent: the studies ran on
one core beside other work). Runs still in progress are drawn to their last evaluation and
marked "partial" in the table.

    python docs/reproductions/long/report.py [STUDY ...]     # default: every study under data/
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA = HERE.parent / "data"
FIGURES = HERE.parent / "figures"
STUDY_PROBLEM = {"oscillators_60min": ("oscillators", 60), "quantum_dipole_90min": ("quantum_dipole", 90),
                 "poisson_hig_b64": ("poisson_hig", None), "sip_navier_stokes": ("navier_stokes", None),
                 "sip_navier_stokes_ws": ("navier_stokes", None)}  # fmt: skip
# the half-inverse route each study's physgrad took (the oscillator and dipole studies ran
# before the structured route existed)
STUDY_ROUTE = {"poisson_hig_b64": "structured"}


def calibration() -> dict[tuple[str, str, str], float]:
    """(problem, method, route) -> seconds per step measured alone (route '' for the others)."""
    with (HERE / "calibration.csv").open() as f:
        return {(r["problem"], r["method"], r["route"]): float(r["ms_per_step"]) / 1e3 for r in csv.DictReader(f)}


def seconds(cal, study: str, method: str, step):
    """Calibrated time at ``step`` of a method directory: a sequence such as
    ``adam-1413-hig`` spends its first 1,413 steps at Adam's rate, the rest at HIG's."""
    problem = STUDY_PROBLEM.get(study, (study, None))[0]
    route = STUDY_ROUTE.get(study, "gram")

    def rate(m):
        return cal.get((problem, m, route if m in ("gn", "hig") else ""), math.nan)

    parts = method.split("-")
    if len(parts) == 3:  # first-STEPS-second
        first, n, second = parts[0], int(parts[1]), parts[2]
        step = np.asarray(step, float)
        return np.minimum(step, n) * rate(first) + np.maximum(step - n, 0) * rate(second)
    return np.asarray(step, float) * rate(method)


def runs(study: Path, method: str) -> list[dict]:
    """Every run of one method: seed, test-loss curve (step, wall), status and budget."""
    out = []
    for run in sorted((study / method / "runs").glob("*-seed*")):
        metrics = run / "metrics.csv"
        if not metrics.exists():
            continue
        rows = [r for r in csv.DictReader(metrics.open()) if r["split"] == "test" and r["metric"] == "loss"]
        summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else None
        config = json.loads((run / "config.json").read_text())
        out.append({
            "seed": config["seed"], "budget": config["budget"]["steps"],
            "step": np.array([int(r["step"]) for r in rows]), "wall": np.array([float(r["wall_time"]) for r in rows]),
            "loss": np.array([float(r["value"]) for r in rows]),
            "status": summary["status"] if summary else "partial",
            "last_step": (summary.get("diverged_step") or summary["steps"]) if summary else (int(rows[-1]["step"]) if rows else 0),
        })  # fmt: skip
    return out


def table(study: Path, cal) -> tuple[list[str], dict]:
    problem, minutes = STUDY_PROBLEM.get(study.name, (study.name, None))
    methods = sorted(p.name for p in study.iterdir() if (p / "runs").is_dir())
    data = {m: runs(study, m) for m in methods}
    finals = {}
    lines = [f"| method | s/step alone | budget (steps) | runs | final test loss (mean ± std) | / adam | state |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for m in methods:
        rs = data[m]
        done = [r for r in rs if r["status"] == "finished"]
        div = [r for r in rs if r["status"] == "diverged"]
        values = np.array([r["loss"][-1] for r in done if len(r["loss"])])
        finals[m] = values
        state = ", ".join(f"seed {r['seed']}: {r['status']} at step {r['last_step']}"
                          for r in rs if r["status"] != "finished") or "all finished"  # fmt: skip
        mean = f"{values.mean():.3e} ± {values.std(ddof=1) if len(values) > 1 else 0:.1e}" if len(values) else "-"
        per_step = float(seconds(cal, study.name, m, 1)) if "-" not in m else math.nan
        lines.append(f"| {m} | {per_step:.4f} | {rs[0]['budget'] if rs else '-'} | "
                     f"{len(done)} finished, {len(div)} diverged | {mean} | RATIO_{m} | {state} |")  # fmt: skip
    base = finals.get("adam")
    for i, line in enumerate(lines):
        for m in methods:
            if f"RATIO_{m}" in line:
                ok = base is not None and len(base) and len(finals[m])
                lines[i] = line.replace(f"RATIO_{m}", f"{finals[m].mean() / base.mean():.3g}" if ok else "-")
    return lines, data


def figure(study: Path, data: dict, cal, out: Path):
    problem, minutes = STUDY_PROBLEM.get(study.name, (study.name, None))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for m, rs in sorted(data.items()):
        for r in rs:
            if not len(r["loss"]):
                continue
            t = seconds(cal, study.name, m, r["step"]) / 60
            style = dict(alpha=0.8, lw=1, label=f"{m} seed {r['seed']}" + (" (diverged)" if r["status"] == "diverged" else ""))
            axes[0].semilogy(t, r["loss"], **style)
            axes[1].semilogy(r["wall"] / 60, r["loss"], **style)
    axes[0].set_xlabel("calibrated time (min): step × s/step measured alone")
    axes[1].set_xlabel("raw training wall-clock (min, one core under load)")
    axes[0].set_ylabel("test loss")
    if minutes:
        axes[0].axvline(minutes, color="k", ls=":", lw=1)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{problem}: long study ({study.name})")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(names: list[str]):
    cal = calibration()
    studies = [DATA / n for n in names] if names else sorted(p for p in DATA.iterdir() if p.is_dir())
    for study in studies:
        lines, data = table(study, cal)
        out = FIGURES / f"long_{study.name}.png"
        figure(study, data, cal, out)
        print(f"### {study.name}\n")
        print("\n".join(lines))
        print(f"\n![{study.name}](figures/{out.name})\n")


if __name__ == "__main__":
    main(sys.argv[1:])

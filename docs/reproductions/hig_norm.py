"""HIG's step size η against the loss normalisation: a sweep on the 8×8 Poisson problem.

The shipped ``poisson_hig`` loss sums over the 64 cells, L_i = ½ Σ_k (∇²x − y*)_k². The same
problem with the loss a *mean* over the cells, L_i / 64, has the same minimiser and the
same Jacobian J, but an output gradient g 64× smaller. HIG's direction V Σ^{−½} Uᵀ g is
linear in g, so with θ ← θ − η d the mean-loss run at η takes the step of the sum-loss run
at η / 64; Adam's update does not change (apart from its ε). This script measures what that
does at the rates a user would try: HIG (SGD, τ = 1e-5, the problem's defaults) at
η ∈ {0.01, 0.1, 1, 10, 100, 1000} (and 64 on the mean loss: the sum's η = 1) and Adam at
lr ∈ {1e-4, 3e-4, 1e-3, 3e-3, 1e-2} (3e-4 is the problem's documented rate), under both
normalisations, seeds 0–2 (a seed fixes the data and the initial network, shared by every
configuration), batch 8 (a HIG step at the paper's batch 64 costs ~20 s on a CPU core; at
8, ~55 ms), 300 steps each, one evaluation at the end on the 1,024 test samples. Equal
steps, not equal time: a HIG step costs a few hundred Adam steps here
(``cpu_ms_per_step`` in the CSV).

    nice -n 19 python docs/reproductions/hig_norm.py run      # ~11 CPU minutes; writes hig_norm.csv
    python docs/reproductions/hig_norm.py report              # the table of docs/methods.md from the CSV

The CSV has one row per run: ``normalisation`` (``sum``: shipped; ``mean``: over the cells),
``method``, ``lr``, ``seed``, ``status``, ``steps``, ``test_loss`` (in the run's own loss),
``test_loss_sum`` (in the shipped ½Σ units, i.e. ×64 for ``mean``, so rows compare),
``x_l1`` (mean |x − x_gt|, independent of the normalisation) and ``cpu_ms_per_step``.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path
from typing import ClassVar

CSV = Path(__file__).with_suffix(".csv")
NORMALISATIONS = ("sum", "mean")
RATES = {"hig": (0.01, 0.1, 1.0, 10.0, 100.0, 1000.0), "adam": (1e-4, 3e-4, 1e-3, 3e-3, 1e-2)}
# and HIG on the mean loss at η = 64, whose steps are those of the sum loss at η = 1 up to rounding
MATCHED = {("mean", "hig"): (64.0,)}
SEEDS = (0, 1, 2)
BATCH, STEPS, TRUNCATION = 8, 300, 1e-5
FIELDS = ("normalisation", "method", "lr", "seed", "status", "steps", "test_loss", "test_loss_sum", "x_l1",
          "cpu_ms_per_step")  # fmt: skip


def problems():
    """``{"sum": PoissonHig(), "mean": the same with the loss divided by the cells}``."""
    from physgrad.problems import PoissonHig

    class PoissonHigCellMean(PoissonHig):
        """poisson_hig with the per-sample loss a mean over the 64 cells: ½ mean_k (∇²x − y*)_k²."""

        name: ClassVar[str] = "poisson_hig_cell_mean"

        def loss(self, y, sample):
            return super().loss(y, sample) / self.size

    return {"sum": PoissonHig(), "mean": PoissonHigCellMean()}


def method(name: str, lr: float):
    import optax

    import physgrad
    from physgrad.methods import Gradient, JacobianPower

    if name == "hig":
        return physgrad.Method(JacobianPower(-0.5, TRUNCATION), optax.sgd(lr))
    return physgrad.Method(Gradient(), optax.adam(lr))


def run(out: Path) -> None:
    import physgrad

    done = set()
    if out.exists():  # resume: keep the rows already written
        with out.open() as f:
            done = {(r["normalisation"], r["method"], float(r["lr"]), int(r["seed"])) for r in csv.DictReader(f)}
    new = not out.exists()
    with out.open("a", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        if new:
            writer.writeheader()
        for normalisation, problem in problems().items():
            cells = 1 if normalisation == "sum" else problem.size
            for name, rates in RATES.items():
                for lr in rates + MATCHED.get((normalisation, name), ()):
                    rule = method(name, lr)  # one object per configuration: its seeds share the compiled step
                    for seed in SEEDS:
                        if (normalisation, name, lr, seed) in done:
                            continue
                        result = physgrad.fit(
                            problem, rule, budget=physgrad.Budget(steps=STEPS), seed=seed, batch_size=BATCH,
                            settings=physgrad.TrainSettings(eval_every=STEPS), progress=False, name=name,
                        )  # fmt: skip
                        s = result.summary
                        loss = s["final_test_loss"] if s["status"] != "diverged" else math.nan
                        x_l1 = s["final_test_metrics"].get("x_l1", math.nan) if s["status"] != "diverged" else math.nan
                        row = {
                            "normalisation": normalisation, "method": name, "lr": lr, "seed": seed,
                            "status": s["status"], "steps": s["steps"], "test_loss": f"{loss:.6g}",
                            "test_loss_sum": f"{loss * cells:.6g}", "x_l1": f"{x_l1:.6g}",
                            "cpu_ms_per_step": f"{1e3 * (s['cpu_time_per_step'] or math.nan):.3g}",
                        }  # fmt: skip
                        writer.writerow(row)
                        f.flush()
                        print(" ".join(f"{k}={v}" for k, v in row.items()), flush=True)


def report(path: Path) -> str:
    """Markdown: per normalisation, method and rate, the three seeds' test loss in ½Σ units."""
    with path.open() as f:
        rows = list(csv.DictReader(f))
    groups: dict[tuple[str, str, float], list[dict[str, str]]] = {}
    for r in rows:
        groups.setdefault((r["method"], r["normalisation"], float(r["lr"])), []).append(r)
    lines = [
        "| method | loss normalised as | η (lr) | test loss ½Σ, seeds 0, 1, 2 | mean | x_l1 (mean) |",
        "|---|---|---|---|---|---|",
    ]
    for (name, normalisation, lr), runs in sorted(groups.items(), key=lambda kv: (kv[0][0] != "hig", kv[0])):
        runs.sort(key=lambda r: int(r["seed"]))
        losses = [float(r["test_loss_sum"]) for r in runs]
        x_l1 = [float(r["x_l1"]) for r in runs]
        seeds = ", ".join("diverged" if math.isnan(v) else f"{v:.3g}" for v in losses)
        mean = "–" if any(math.isnan(v) for v in losses) else f"{sum(losses) / len(losses):.3g}"
        xm = "–" if any(math.isnan(v) for v in x_l1) else f"{sum(x_l1) / len(x_l1):.3g}"
        lines.append(f"| {name} | {normalisation} | {lr:g} | {seeds} | {mean} | {xm} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("run", "report"))
    parser.add_argument("--csv", type=Path, default=CSV)
    args = parser.parse_args(argv)
    if args.what == "run":
        run(args.csv)
    else:
        print(report(args.csv))


if __name__ == "__main__":
    main(sys.argv[1:])

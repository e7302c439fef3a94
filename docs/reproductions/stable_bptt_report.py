"""Tables and figures of docs/reproductions/stable_bptt.md, from the sweep directories alone.

Run the sweeps first (docs/reproductions/stable_bptt_runs.sh), then

    python docs/reproductions/stable_bptt_report.py [--studies docs/reproductions/data/short/stable_bptt] [--smooth 10]

reads the study-level files that keep_studies.py copied into docs/reproductions/data/short/stable_bptt
(committed, so a clone redraws the report; ``--studies studies/stable_bptt`` reads a fresh run's), and
prints, per task, a Markdown table of the final test loss (each seed's mean over its last
10 % of epochs, then mean ± std over seeds) per
complexity setting × method × clip mode, the best method per setting, and writes the panel
figures (one panel per complexity setting, as the paper's Figs. 3-5) to
docs/reproductions/figures/stable_bptt_*.png: test loss, the squared gradient norm
("update size") and, for C, the cosine between g_M and g_R.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from physgrad.harness.study import cell_name, grid_cells, grid_report, kept_path, markdown, read_csv

FIGURES = Path(__file__).parent / "figures"
# the committed study-level files of its studies (keep_studies.py copies them there)
KEPT = Path(__file__).parent / "data" / "short" / "stable_bptt"
TASKS = {  # directory: (title, the complexity setting)
    "cartpole": ("Cart-pole swing-up (paper Fig. 4)", "poles"),
    "cartpole-1000ep": ("Cart-pole, 4 poles, R vs C at the paper's 1000 epochs", "poles"),
    "guidance": ("Guidance by repulsion (paper Fig. 3)", "rc"),
    "quantum_control": ("Quantum control (paper Fig. 5)", "eigenstate"),
    "quantum_control-250ep": ("Quantum control, eigenstate 5, R vs M vs C at 250 epochs", "eigenstate"),
}
LABELS = {"bptt": "R (bptt)", "sbptt_m": "M (sbptt_m)", "sbptt_c": "C (sbptt_c)", "no_temporal": "S (no_temporal)"}


TAIL = 0.1  # the table's "final" loss: each seed's mean over its last 10 % of epochs


def cell(mean: float, std: float, diverged: int = 0, runs: int = 0) -> str:
    text = f"{mean:.2e} ± {std:.0e}" if math.isfinite(mean) else "diverged"
    return text + (f" ({diverged}/{runs} div.)" if diverged and math.isfinite(mean) else "")


def seed_tails(results, method: str, diverged: set) -> list[float]:
    """Each finished seed's mean test loss over its last 10 % of epochs (a diverged seed,
    listed in ``diverged``, is left out: its curve stops where it turned NaN)."""
    by_seed: dict[str, list[tuple[int, float]]] = {}
    for r in results:
        if r["method"] == method and r["split"] == "test" and r["metric"] == "loss" and r["seed"] not in diverged:
            by_seed.setdefault(r["seed"], []).append((int(r["step"]), float(r["value"])))
    out = []
    for points in by_seed.values():
        points.sort()
        end = points[-1][0]
        out.append(float(np.mean([v for t, v in points if t >= (1 - TAIL) * end])))
    return out


def tail_losses(out: Path, grid: dict, methods) -> dict:
    """(cell values, method) -> (mean, std) over finished seeds of the last-10 %-of-epochs
    test loss, and (cell values, method, "seeds") -> the per-seed values (the curves are
    noisy per epoch; the authors' plots smooth over 30 epochs)."""
    table = {}
    for values in grid_cells(grid):
        path = kept_path(out / cell_name(values) / "results.csv")  # or results.csv.gz
        if not path.exists():
            continue
        results = read_csv(path)
        summary = read_csv(out / cell_name(values) / "summary.csv")
        for method in methods:
            diverged = {r["seed"] for r in summary if r["method"] == method and r["status"] == "diverged"}
            seeds = np.array(seed_tails(results, method, diverged))
            mean = float(seeds.mean()) if seeds.size else math.nan
            std = float(seeds.std(ddof=1)) if seeds.size > 1 else 0.0
            table[(tuple(values.values()), method)] = (mean, std)
            table[(tuple(values.values()), method, "seeds")] = list(seeds)
    return table


def task_section(root: Path, task: str, smooth: int) -> str:
    title, setting = TASKS[task]
    out = root / task
    if not (out / "grid.json").exists():
        return f"## {title}: no sweep under {out} yet\n"
    info = json.loads((out / "grid.json").read_text())
    report = grid_report(
        out,
        panel=setting,
        smooth=smooth,
        methods=list(LABELS),
        figure=FIGURES / f"stable_bptt_{task.replace('-', '_')}.png",
    )
    grid_report(out, panel=setting, metric="step_grad_norm2", split="train", smooth=smooth, methods=list(LABELS),
                figure=FIGURES / f"stable_bptt_{task.replace('-', '_')}_grad_norm2.png")  # fmt: skip
    clips = info["grid"].get("clip", [""])
    values = info["grid"][setting]
    rows = {(r[setting], r.get("clip", ""), r["method"]): r for r in report.rows}
    tails = tail_losses(out, info["grid"], info["methods"])
    lines = [[setting, "method"] + [f"clip {c}" for c in clips] + ["best clip"]]
    best_lines = [[setting, "best method (its best clip mode)", "ranking by best final test loss"]]
    pooled = [[setting] + [f"{LABELS.get(m, m)}" for m in info["methods"]]]
    for value in values:
        best = {}
        for method in info["methods"]:
            found = [rows.get((value, c, method)) for c in clips]
            stats = [tails.get(((value, c), method), (math.nan, math.nan)) for c in clips]
            finals = [(m, c) for (m, _), r, c in zip(stats, found, clips) if r and math.isfinite(m)]
            best[method] = min(finals) if finals else (math.inf, "-")
            lines.append([value, LABELS.get(method, method)]
                         + [cell(m, sd, r["diverged"], r["runs"]) if r else "-" for (m, sd), r in zip(stats, found)]
                         + [best[method][1]])  # fmt: skip
        line = [value]
        for method in info["methods"]:
            ok = np.array([v for c in clips for v in tails.get(((value, c), method, "seeds"), [])])
            n_div = sum(rows[(value, c, method)]["diverged"] for c in clips if (value, c, method) in rows)
            line.append(f"{np.median(ok):.2e} [{ok.min():.1e}, {ok.max():.1e}]" + (f", {n_div} diverged" if n_div else "")
                        if ok.size else "-")  # fmt: skip
        pooled.append(line)
        ranking = sorted(best, key=lambda m: best[m][0])
        best_lines.append([value, f"{LABELS.get(ranking[0], ranking[0])} ({best[ranking[0]][1]})",
                           " < ".join(f"{LABELS.get(m, m).split()[0]} {best[m][0]:.2e}" for m in ranking)])  # fmt: skip
    budget = ", ".join(f"{v:g} {k}" for k, v in info["budget"].items())
    name = task.replace("-", "_")
    figures = [f"![{title}: test loss](figures/stable_bptt_{name}.png)",
               f"![{title}: squared gradient norm](figures/stable_bptt_{name}_grad_norm2.png)"]  # fmt: skip
    return "\n".join([
        f"## {title}: {budget} per run, {len(info['seeds'])} seeds",
        "",
        "Final test loss (each seed's mean over its last 10 % of epochs), mean ± std over seeds; "
        "diverged runs (NaN) are counted and left out of the mean:",
        "",
        markdown(lines),
        "",
        markdown(best_lines),
        "",
        f"All clip modes and seeds pooled ({len(clips) * len(info['seeds'])} runs per cell): median [min, max] "
        "of the finished runs' final test loss:",
        "",
        markdown(pooled),
        "",
        *figures,
        "",
    ])  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--studies", default=str(KEPT), help="directory holding the study directories (default: the committed ones)"
    )
    parser.add_argument("--smooth", type=int, default=10, help="moving-average window of the figures (epochs)")
    args = parser.parse_args()
    FIGURES.mkdir(exist_ok=True)
    for task in TASKS:
        print(task_section(Path(args.studies), task, args.smooth))


if __name__ == "__main__":
    main()

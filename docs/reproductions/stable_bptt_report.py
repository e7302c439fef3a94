"""Tables and figures of docs/reproductions/stable_bptt.md, from the sweep directories alone.

Run the sweeps first (docs/reproductions/stable_bptt_runs.sh), then

    python docs/reproductions/stable_bptt_report.py [--studies studies/stable_bptt] [--smooth 10]

prints, per task, a Markdown table of the final test loss (mean ± std over seeds) per
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

from physgrad.study import grid_report, markdown

FIGURES = Path(__file__).parent / "figures"
TASKS = {  # directory: (title, the complexity setting)
    "cartpole": ("Cart-pole swing-up (paper Fig. 4)", "poles"),
    "guidance": ("Guidance by repulsion (paper Fig. 3)", "rc"),
    "quantum_control": ("Quantum control (paper Fig. 5)", "eigenstate"),
}
LABELS = {"bptt": "R (bptt)", "sbptt_m": "M (sbptt_m)", "sbptt_c": "C (sbptt_c)", "no_temporal": "S (no_temporal)"}


def cell(mean: float, std: float) -> str:
    return f"{mean:.2e} ± {std:.0e}" if math.isfinite(mean) else "diverged"


def task_section(root: Path, task: str, smooth: int) -> str:
    title, setting = TASKS[task]
    out = root / task
    if not (out / "grid.json").exists():
        return f"## {title}: no sweep under {out} yet\n"
    info = json.loads((out / "grid.json").read_text())
    report = grid_report(out, panel=setting, smooth=smooth, figure=FIGURES / f"stable_bptt_{task}.png")
    grid_report(out, panel=setting, metric="step_grad_norm2", split="train", smooth=smooth,
                figure=FIGURES / f"stable_bptt_{task}_grad_norm2.png")  # fmt: skip
    clips = info["grid"].get("clip", [""])
    values = info["grid"][setting]
    rows = {(r[setting], r.get("clip", ""), r["method"]): r for r in report.rows}
    lines = [[setting, "method"] + [f"clip {c}" for c in clips] + ["best clip"]]
    best_lines = [[setting, "best method (its best clip mode)", "ranking by best final test loss"]]
    for value in values:
        best = {}
        for method in info["methods"]:
            found = [rows.get((value, c, method)) for c in clips]
            finals = [(r["final_test_loss"], c) for r, c in zip(found, clips) if r and math.isfinite(r["final_test_loss"])]
            best[method] = min(finals) if finals else (math.inf, "-")
            lines.append([value, LABELS.get(method, method)]
                         + [cell(r["final_test_loss"], r["final_test_loss_std"]) if r else "-" for r in found]
                         + [best[method][1]])  # fmt: skip
        ranking = sorted(best, key=lambda m: best[m][0])
        best_lines.append([value, f"{LABELS.get(ranking[0], ranking[0])} ({best[ranking[0]][1]})",
                           " < ".join(f"{LABELS.get(m, m).split()[0]} {best[m][0]:.2e}" for m in ranking)])  # fmt: skip
    budget = ", ".join(f"{v:g} {k}" for k, v in info["budget"].items())
    figures = [f"![{title}: test loss](figures/stable_bptt_{task}.png)",
               f"![{title}: squared gradient norm](figures/stable_bptt_{task}_grad_norm2.png)"]  # fmt: skip
    return "\n".join([
        f"## {title}: {budget} per run, {len(info['seeds'])} seeds",
        "",
        "Final test loss (last epoch), mean ± std over seeds:",
        "",
        markdown(lines),
        "",
        markdown(best_lines),
        "",
        *figures,
        "",
    ])  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--studies", default="studies/stable_bptt")
    parser.add_argument("--smooth", type=int, default=10, help="moving-average window of the figures (epochs)")
    args = parser.parse_args()
    FIGURES.mkdir(exist_ok=True)
    for task in TASKS:
        print(task_section(Path(args.studies), task, args.smooth))


if __name__ == "__main__":
    main()

"""Tables and figures of docs/reproductions/hig.md, from the study directories alone.

Run the studies first (docs/reproductions/hig_runs.sh), then

    python docs/reproductions/hig_report.py [--studies studies/hig]

prints one Markdown table per problem (final test loss mean ± std over seeds, best test
loss, steps, ms/step, ratio to Adam) and writes the figures to docs/reproductions/figures/.
Studies of one problem that differ only in a setting (Poisson at the paper's batch and at
batch 8) are merged, their methods labelled with the setting.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from physgrad.plots import loss_vs_time
from physgrad.study import aggregate, final_metric, format_table, load_studies, markdown

FIGURES = Path(__file__).parent / "figures"

# figure name -> (title, [(study directory, label suffix for its methods)], metrics to plot)
REPORTS = {
    "hig_toy_lam0.01": ("HIG toy, λ = 0.01", [("toy_lam0.01", "")], ["loss"]),
    "hig_toy_lam1": ("HIG toy, λ = 1", [("toy_lam1", "")], ["loss"]),
    "oscillators": ("Nonlinear oscillators (HIG paper Fig. 2b)", [("oscillators", "")], ["loss"]),
    "quantum_dipole": ("Quantum dipole", [("quantum_dipole", "")], ["loss"]),
    "poisson_hig": (
        "Poisson 8×8",
        [("poisson_hig", ""), ("poisson_hig_b8", " (b8)")],
        ["loss", "x_l1"],
    ),
    "linear_oscillators": ("Linear oscillators (PBDL book)", [("linear_oscillators", "")], ["loss"]),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--studies", default="studies/hig", help="directory holding the study directories")
    args = parser.parse_args()
    root = Path(args.studies)
    FIGURES.mkdir(parents=True, exist_ok=True)
    for key, (title, parts, metrics) in REPORTS.items():
        rows, results, order = load_studies(root, parts)
        if not rows:
            print(f"## {title}: no results under {root} yet\n")
            continue
        table = aggregate(rows, order)
        lines = format_table(table, "adam" if "adam" in order else None)
        for metric in metrics[1:]:
            lines[0].append(f"final test {metric}")
            for line in lines[1:]:
                mean, std = final_metric(results, line[0], metric)
                line.append(f"{mean:.3e} ± {std:.1e}")
        seeds = len({r["seed"] for r in rows})
        print(f"## {title} ({seeds} seeds)\n\n{markdown(lines)}\n")
        notes = {t["method"]: f"{t['diverged']}/{t['runs']} diverged" for t in table if t["diverged"]}
        for metric in metrics:
            name = key if metric == "loss" else f"{key}_{metric}"
            path = loss_vs_time(
                results, FIGURES / f"{name}.png", order=order, metric=metric, notes=notes,
                title=f"{title}: test {metric}, {seeds} seeds (line: geometric mean, band: min-max)",
            )  # fmt: skip
            print(f"![{title}](figures/{path.name})\n")


if __name__ == "__main__":
    main()

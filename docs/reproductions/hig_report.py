"""Tables and figures of docs/reproductions/hig.md, from the study directories alone.

Run the studies first (docs/reproductions/hig_runs.sh), then

    python docs/reproductions/hig_report.py [--studies docs/reproductions/data/short/hig]

reads the study-level files that keep_studies.py copied into docs/reproductions/data/short/hig
(committed, so a clone redraws the report; ``--studies studies/hig`` reads a fresh run's), and
prints one Markdown table per problem (final test loss mean ± std over seeds, best test
loss, steps, ms/step, ratio to Adam) and writes the figures to docs/reproductions/figures/.
Studies of one problem that differ only in a setting (Poisson at the paper's batch and at
batch 8) are merged, their methods labelled with the setting.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from physgrad.harness.study import study_section

FIGURES = Path(__file__).parent / "figures"
# the committed study-level files of its studies (keep_studies.py copies them there)
KEPT = Path(__file__).parent / "data" / "short" / "hig"

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
    parser.add_argument(
        "--studies", default=str(KEPT), help="directory holding the study directories (default: the committed ones)"
    )
    args = parser.parse_args()
    root = Path(args.studies)
    FIGURES.mkdir(parents=True, exist_ok=True)
    for key, (title, parts, metrics) in REPORTS.items():
        print(study_section(root, title, parts, metrics, FIGURES, key))


if __name__ == "__main__":
    main()

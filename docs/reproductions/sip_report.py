"""Tables and figures of docs/reproductions/sip.md, from the study directories alone.

Run the studies first (docs/reproductions/sip_runs.sh), then

    python docs/reproductions/sip_report.py [--studies docs/reproductions/data/short/sip]

reads the study-level files that keep_studies.py copied into docs/reproductions/data/short/sip
(committed, so a clone redraws the report; ``--studies studies/sip`` reads a fresh run's), and
prints one Markdown table per problem (final test loss and x-space errors, mean ± std over
seeds) and writes the figures to docs/reproductions/figures/sip_*.png: the 2D toy's
trajectories in x and y, the sine sweeps over ξ and φ, and error-vs-wall-clock curves.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from physgrad.harness.study import final_metric, kept_path, load_studies, markdown, read_csv, study_section

FIGURES = Path(__file__).parent / "figures"
# the committed study-level files of its studies (keep_studies.py copies them there)
KEPT = Path(__file__).parent / "data" / "short" / "sip"
XI_SWEEP = (1, 4, 16, 64)  # at φ = 0
PHI_SWEEP = (0, 15, 30, 45)  # at ξ = 32

# figure name -> (title, study directory, metrics: the first is the table's loss)
REPORTS = {
    "sip_exp_inverse": ("exp inverse (SIP Fig. 2)", "exp_inverse", ["loss", "x_l1", "x_l1_low", "x_l1_high"]),
    "sip_linear_oscillators": ("Linear oscillators (PBDL book)", "linear_oscillators", ["loss"]),
    # 100 steps: the first iteration at which the authors' plot script compares Adam with SIP
    "sip_poisson": ("Poisson 64×64, 100 steps (SIP Fig. 6a,b)", "poisson-100", ["loss", "x_l1"]),
    "sip_heat": ("Heat 64×64, 100 steps (SIP Fig. 6c,d)", "heat-100", ["loss", "x_l1", "x_l1_clamped"]),
    "sip_heat_direct": (
        "Heat without a network (direct optimisation)",
        "heat-direct",
        ["loss", "x_l1", "x_l1_clamped"],
    ),
    "sip_sine_xi32_phi45": ("Sine ξ = 32, φ = 45°", "sine-xi32-phi45", ["loss", "x_dist"]),
}


def problem_tables(root: Path):
    for key, (title, study, metrics) in REPORTS.items():
        print(study_section(root, title, [(study, "")], metrics, FIGURES, key))


def toy(root: Path):
    """End points and the trajectory figure of the 2D toy (10 iterations from (3, 3))."""
    path = kept_path(root / "toy2d" / "results.csv")  # or its gzipped copy
    if not path.exists():
        print("## 2D toy: no results yet\n")
        return
    paths: dict[str, dict[int, dict[str, float]]] = {}
    for r in read_csv(path):
        if r["split"] == "test" and r["metric"] in ("x0", "x1", "y0", "y1"):
            paths.setdefault(r["method"], {}).setdefault(int(r["step"]), {})[r["metric"]] = float(r["value"])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_x, ax_y) = plt.subplots(1, 2, figsize=(9, 4), dpi=120)
    labels = {"sgd": "GD (η 0.01)", "newton": "Newton (η 1/3)", "sip": "inverse simulator (η 0.3)"}
    lines = [
        ["method", "x after 10 iterations", "y after 10 iterations", "\\|x\\|", "L = \\|y\\|²"]
    ]  # pipes escaped for Markdown
    for method, steps in paths.items():
        order = sorted(steps)
        xs = np.array([[steps[k]["x0"], steps[k]["x1"]] for k in order])
        ys = np.array([[steps[k]["y0"], steps[k]["y1"]] for k in order])
        ax_x.plot(*xs.T, "o-", ms=3, label=labels.get(method, method))
        ax_y.plot(*ys.T, "o-", ms=3, label=labels.get(method, method))
        lines.append([
            labels.get(method, method), f"({xs[-1, 0]:.4f}, {xs[-1, 1]:.4f})", f"({ys[-1, 0]:.4f}, {ys[-1, 1]:.4f})",
            f"{np.linalg.norm(xs[-1]):.4f}", f"{np.sum(ys[-1] ** 2):.3e}",
        ])  # fmt: skip
    for ax, name in ((ax_x, "x"), (ax_y, "y")):
        ax.plot(0, 0, "k*", ms=10)
        ax.set_xlabel(f"{name}₀")
        ax.set_ylabel(f"{name}₁")
        ax.set_title(f"trajectories in {name} (10 iterations from x = (3, 3))", fontsize=9)
        ax.grid(alpha=0.3)
    ax_x.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(FIGURES / "sip_toy2d.png")
    plt.close(fig)
    print(f"## 2D toy\n\n{markdown(lines)}\n\n![2D toy](figures/sip_toy2d.png)\n")


def sine_sweeps(root: Path):
    """x-distance (average of the last 10 % of training time, mean ± std over seeds) of Adam
    and SIP along the paper's ξ sweep (φ = 0, relative: / ξ) and φ sweep (ξ = 32)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sweeps = {
        "xi": ("ξ (φ = 0°)", [(xi, f"sine-xi{xi}-phi0") for xi in XI_SWEEP], "x_dist_rel"),
        "phi": ("φ [°] (ξ = 32)", [(phi, f"sine-xi32-phi{phi}") for phi in PHI_SWEEP], "x_dist"),
    }
    if not any(load_studies(root, [(study, "")])[1] for _, points, _ in sweeps.values() for _, study in points):
        # no sweep has results: keep the committed figure rather than draw empty axes over it
        print(f"## Sine sweeps: no results under {root} yet\n")
        return
    fig, axes = plt.subplots(1, 2, figsize=(9, 4), dpi=120)
    for ax, (name, (label, points, metric)) in zip(axes, sweeps.items()):
        lines = [[label, "Adam", "SIP", "Adam / SIP"]]
        curves: dict[str, list[tuple[float, float, float]]] = {"adam": [], "sip": []}
        for value, study in points:
            _, results, _ = load_studies(root, [(study, "")])
            if not results:
                continue
            cells = {}
            for method in curves:
                mean, std = final_metric(results, method, metric, tail=0.1)
                curves[method].append((value, mean, std))
                cells[method] = (mean, std)
            lines.append([str(value)] + [f"{cells[m][0]:.2e} ± {cells[m][1]:.0e}" for m in curves]
                         + [f"{cells['adam'][0] / cells['sip'][0]:.1f}"])  # fmt: skip
        for method, pts in curves.items():
            if pts:
                v, m, s = np.array(pts).T
                ax.errorbar(v, m, yerr=s, marker="o", capsize=3, label={"adam": "Adam", "sip": "SIP"}[method])
        ax.set_yscale("log")
        if name == "xi":
            ax.set_xscale("log", base=2)
        ax.set_xlabel(label)
        ax.set_ylabel(f"test {metric} (last 10 % of time)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        print(f"## Sine sweep over {label}: test {metric}, mean ± std over seeds\n\n{markdown(lines)}\n")
    fig.tight_layout()
    fig.savefig(FIGURES / "sip_sine_sweeps.png")
    plt.close(fig)
    print("![sine sweeps](figures/sip_sine_sweeps.png)\n")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--studies", default=str(KEPT), help="directory holding the study directories (default: the committed ones)"
    )
    root = Path(parser.parse_args().studies)
    FIGURES.mkdir(parents=True, exist_ok=True)
    toy(root)
    problem_tables(root)
    sine_sweeps(root)


if __name__ == "__main__":
    main()

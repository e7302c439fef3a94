"""Tables and figures of docs/reproductions/unrolling.md, from the study directories alone.

Run the studies first (docs/reproductions/unrolling_runs.sh LANE), then

    python docs/reproductions/unrolling_report.py [--studies docs/reproductions/data/short/unrolling]

reads the study-level files that keep_studies.py copied into docs/reproductions/data/short/unrolling
(committed, so a clone redraws the report; ``--studies studies/unrolling`` reads a fresh run's), and
prints Markdown sections (KS, Kolmogorov, advection, PRDP) and writes the figures to
docs/reproductions/figures/unrolling_*.png. Errors are each run's final metrics on every
test case (``test_cases.json``): per seed the mean over test cases, then mean ± std over
seeds; paired tests are two-sided Wilcoxon signed-rank tests over (seed, test case) pairs.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from physgrad.harness.stats import case_values, format_p, format_ratio, paired_tests, seed_means
from physgrad.harness.study import collect, kept_path, markdown, read_csv

FIGURES = Path(__file__).parent / "figures"
# the committed study-level files of its studies (keep_studies.py copies them there)
KEPT = Path(__file__).parent / "data" / "short" / "unrolling"
METHODS = ("one", "nog", "wig")
SETUPS = ("correction", "prediction")


def fmt(mean: float, std: float) -> str:
    return f"{mean:.2e} ± {std:.0e}" if math.isfinite(mean) else "—"


def runs(cell: Path) -> list[dict]:
    """The finished runs of a study (re-collected, so a study still running counts its
    finished runs)."""
    if (cell / "study.json").exists():
        collect(cell)
    return read_csv(cell / "summary.csv") if (cell / "summary.csv").exists() else []


def curve(cell: Path, method: str, metric: str, split: str = "test"):
    """{seed: (epochs, values)} of one method's evaluations."""
    out: dict[str, tuple[list, list]] = {}
    if not kept_path(cell / "results.csv").exists():  # or its gzipped copy
        return out
    summary = {r["seed"]: r for r in runs(cell) if r["method"] == method}
    for r in read_csv(cell / "results.csv"):
        if r["method"] == method and r["split"] == split and r["metric"] == metric and r["seed"] in summary:
            steps_per_epoch = float(summary[r["seed"]]["steps"]) / max(float(summary[r["seed"]]["epochs"]), 1e-12)
            xs, ys = out.setdefault(r["seed"], ([], []))
            xs.append(int(r["step"]) / steps_per_epoch)
            ys.append(float(r["value"]))
    return out


# where the current runs of a problem whose short studies are not kept are drawn instead
LONG_STUDIES = {
    "ks": "ks_correction_2ep_grouped ks_prediction_2ep_grouped ks_correction_20ep_grouped ks_prediction_20ep_grouped",
    "kolmogorov": "kolmogorov_16_2ep_correction kolmogorov_16_2ep_prediction kolmogorov_zero_init_grouped kolmogorov_32",
}


def modality_section(root: Path, problem: str, title: str) -> str:
    """Table (rel_error, corr_time, divergence) per setup x modality, ratios to ONE, paired
    tests, NOG-correction vs WIG-prediction, and the error-vs-epoch figure. Where the
    directory holds no runs of the problem (the committed one: its current runs are long
    studies), a pointer to the command that draws them."""
    import matplotlib.pyplot as plt

    cells = {s: root / f"{problem}_{s}" / f"setup{s}" for s in SETUPS}
    if not any(runs(c) for c in cells.values()):
        return (
            f"## {title}\n\nThe current runs are long studies (the authors' batching), kept under "
            f"docs/reproductions/data/ and drawn by\n`python docs/reproductions/long/report.py {LONG_STUDIES[problem]}`.\n"
        )
    head = [
        "setup",
        "method",
        "seeds",
        "rel_error (12 steps)",
        "/ ONE",
        "corr_time (steps)",
        "diverged",
        "steps",
        "ms/step",
    ]
    lines = [head]
    for setup, cell in cells.items():
        rel, corr, div = seed_means(cell, "rel_error"), seed_means(cell, "corr_time"), seed_means(cell, "diverged")
        rows = runs(cell)
        for method in METHODS:
            if method not in rel:
                continue
            mine = [r for r in rows if r["method"] == method]
            ratio = rel[method][0] / rel["one"][0] if "one" in rel else math.nan
            lines.append([setup, method, str(rel[method][2]), fmt(*rel[method][:2]), f"{ratio:.2f}",
                          f"{corr[method][0]:.1f} ± {corr[method][1]:.1f}", f"{100 * div[method][0]:.0f}%",
                          str(int(np.mean([float(r['steps']) for r in mine]))),
                          f"{1e3 * np.mean([float(r['time_per_step']) for r in mine]):.1f}"])  # fmt: skip
    out = [f"## {title}\n", markdown(lines), ""]
    tests = [["setup", "pair", "pairs", "first lower", "seeds lower", "mean ratio", "Wilcoxon p"]]
    for setup, cell in cells.items():
        for t in paired_tests(cell, "rel_error", list(METHODS)) if runs(cell) else []:
            tests.append([setup, f"{t['method_a']} vs {t['method_b']}", str(t["pairs"]), f"{100 * t['a_lower']:.0f}%",
                          f"{t['seeds_a_lower']}/{t['seeds']}", format_ratio(t["ratio"]), format_p(t["p_value"])])  # fmt: skip
    cross = cross_test(cells["correction"], "nog", cells["prediction"], "wig")
    if cross:
        tests.append(["NOG-correction vs WIG-prediction", "nog vs wig", str(cross["pairs"]),
                      f"{100 * cross['a_lower']:.0f}%", cross["seeds"], format_ratio(cross["ratio"]), format_p(cross["p_value"])])  # fmt: skip
    out += [
        "Paired tests on rel_error (two-sided Wilcoxon signed-rank over seeds × test cases):\n",
        markdown(tests),
        "",
    ]

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, (setup, cell) in zip(axes, cells.items()):
        for method, colour in zip(METHODS, ("C0", "C1", "C2")):
            for i, (xs, ys) in enumerate(curve(cell, method, "rel_error").values()):
                ax.plot(xs, ys, color=colour, alpha=0.8, label=method.upper() if i == 0 else None)
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_title(f"{problem}: {setup}")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("test rel_error (12-step)")
    axes[0].legend()
    fig.tight_layout()
    FIGURES.mkdir(exist_ok=True)
    path = FIGURES / f"unrolling_{problem}.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    out.append(f"![{title}](figures/{path.name})\n")
    return "\n".join(out)


def cross_test(cell_a: Path, method_a: str, cell_b: Path, method_b: str):
    """A Wilcoxon test between methods of two studies (same seeds and test cases)."""
    from scipy.stats import wilcoxon

    _, a = case_values(cell_a, "rel_error")
    _, b = case_values(cell_b, "rel_error")
    if method_a not in a or method_b not in b:
        return None
    seeds = sorted(set(a[method_a]) & set(b[method_b]))
    x = np.concatenate([a[method_a][s] for s in seeds])
    y = np.concatenate([b[method_b][s] for s in seeds])
    lower = sum(np.mean(a[method_a][s]) < np.mean(b[method_b][s]) for s in seeds)
    return {"pairs": len(x), "a_lower": float(np.mean(x < y)), "ratio": float(np.mean(x) / np.mean(y)),
            "seeds": f"{lower}/{len(seeds)}", "p_value": float(wilcoxon(x, y).pvalue)}  # fmt: skip


def advection_section(root: Path) -> str:
    from physgrad.harness.train import load_network
    from physgrad.problems.advection_1d import fou_distance

    out = ["## Advection (trainax quick-start)\n"]
    quick = root / "advection_quickstart"
    lines = [["m (rollout steps)", "seeds", "‖w − FOU‖", "trainax README", "test rel_error"]]
    for m, readme in (("1", "0.033"), ("5", "0.025"), ("20", "0.017")):
        cell = quick / f"m{m}"
        dist = [fou_distance(load_network(cell / r["run_dir"])) for r in runs(cell)]
        rel = seed_means(cell, "rel_error").get("wig")
        if dist:
            lines.append(
                [m, str(len(dist)), f"{np.mean(dist):.3f} ± {np.std(dist, ddof=1):.3f}", readme, fmt(*rel[:2])]
            )
    out += [markdown(lines), ""]
    modalities = root / "advection_modalities"
    lines = [["setup", "one", "nog", "wig"]]
    for setup in ("prediction", "correction"):
        rel = seed_means(modalities / f"setup{setup}", "rel_error")
        if rel:
            lines.append([setup] + [fmt(*rel[m][:2]) if m in rel else "—" for m in METHODS])
    out += ["Test rel_error of the three modalities at m = 5 (1000 steps):\n", markdown(lines), ""]
    return "\n".join(out)


def prdp_section(root: Path) -> str:
    import matplotlib.pyplot as plt

    prdp_cell, fixed = root / "prdp" / "prdp_true", root / "prdp_fixed"
    if not runs(prdp_cell) and (root / "prdp").exists():  # a study without a sweep
        prdp_cell = root / "prdp"
    if not runs(prdp_cell):
        return "## PRDP: no results yet\n"
    lines = [["run", "seeds", "final K", "solver iterations", "train s", "test rel_error", "val rel_error"]]

    def row(label, cell):
        rs = runs(cell)
        details = [json.loads((cell / r["run_dir"] / "summary.json").read_text()) for r in rs]
        ks = [d["prdp"]["K"] if d.get("prdp") else json.loads((cell / r["run_dir"] / "config.json").read_text())
              ["problem_settings"]["iterations"] for d, r in zip(details, rs)]  # fmt: skip
        its = [d["solver_iterations"] for d in details]
        secs = [d["train_seconds"] for d in details]
        rel = seed_means(cell, "rel_error").get("wig", (math.nan, math.nan))
        val = [ys[-1] for _, ys in curve(cell, "wig", "rel_error", "val").values()]
        lines.append([label, str(len(rs)), "/".join(str(k) for k in ks), f"{np.mean(its):.0f}",
                      f"{np.mean(secs):.2f} ± {np.std(secs, ddof=1):.2f}", fmt(*rel[:2]),
                      f"{np.mean(val):.2e}" if val else "—"])  # fmt: skip
        return np.mean(secs), np.mean(its)

    prdp_time, prdp_its = row("PRDP (K from 1, cap 20)", prdp_cell)
    full = None
    for k in ("1", "2", "5", "20"):
        cell = fixed / f"iterations{k}"
        if runs(cell):
            result = row(f"fixed K = {k}", cell)
            if k == "20":
                full = result
    out = ["## PRDP on the advection corrector\n", markdown(lines), ""]
    if full:
        out.append(
            f"PRDP against fixed full fidelity (K = 20): {100 * (1 - prdp_time / full[0]):.0f} % less training "
            f"time, {100 * (1 - prdp_its / full[1]):.0f} % fewer solver iterations.\n"
        )
    fig, (ax, axk) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for label, cell, colour in (
        ("PRDP", prdp_cell, "C3"),
        ("K = 20", fixed / "iterations20", "C0"),
        ("K = 1", fixed / "iterations1", "C2"),
    ):
        for i, (xs, ys) in enumerate(curve(cell, "wig", "rel_error", "val").values()):
            ax.plot(xs, ys, color=colour, alpha=0.8, label=label if i == 0 else None)
        for i, (xs, ys) in enumerate(curve(cell, "wig", "solver_iterations", "train").values()):
            axk.plot(xs, ys, color=colour, alpha=0.8, label=label if i == 0 else None)
    ax.set_yscale("log")
    ax.set_ylabel("val rel_error")
    axk.set_ylabel("solver iterations K")
    axk.set_xlabel("epoch")
    ax.legend()
    fig.tight_layout()
    path = FIGURES / "unrolling_prdp.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    out.append(f"![PRDP](figures/{path.name})\n")
    return "\n".join(out)


def solver_baselines() -> str:
    """The coarse solvers alone (network output 0) on the studies' test splits."""
    import jax
    import jax.numpy as jnp

    from physgrad.problems import Kolmogorov, KuramotoSivashinsky

    lines = [["problem", "rel_error (12 steps)", "corr_time", "diverged"]]
    for label, problem in (("ks: ETD1 alone", KuramotoSivashinsky()),
                           ("kolmogorov (16², mode 4): ETDRK2 alone",
                            Kolmogorov(n=16, forcing_mode=4, width=16, blocks=3, frames=400)),
                           ("kolmogorov (32², mode 6, the paper's size): ETDRK2 alone",
                            Kolmogorov(n=32, forcing_mode=6, width=16, blocks=3))):  # fmt: skip
        test = {k: jnp.asarray(v) for k, v in problem.trajectories("test").items()}

        def roll(sample, problem=problem):
            def body(u, _):
                u, _ = problem.step(lambda v, c: jnp.zeros_like(v), u, u, sample["cond"], sample["index"])
                return u, u

            return jax.lax.scan(body, sample["u"][0], None, length=sample["u"].shape[0] - 1)[1]

        ys = jax.jit(jax.vmap(roll))(test)
        met = jax.vmap(lambda y, s, problem=problem: problem.metrics(None, y, s))(ys, test)
        lines.append([label, f"{float(jnp.mean(met['rel_error'])):.2e}", f"{float(jnp.mean(met['corr_time'])):.1f}",
                      f"{100 * float(jnp.mean(met['diverged'])):.0f}%"])  # fmt: skip
    return "## The coarse solvers alone\n\n" + markdown(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--studies", default=str(KEPT), help="directory holding the study directories (default: the committed ones)"
    )
    args = parser.parse_args()
    root = Path(args.studies)
    print(modality_section(root, "ks", "Kuramoto–Sivashinsky (N = 48, m = 3)"))
    print(modality_section(root, "kolmogorov", "Kolmogorov flow"))
    print(advection_section(root))
    print(prdp_section(root))
    print(solver_baselines())


if __name__ == "__main__":
    main()

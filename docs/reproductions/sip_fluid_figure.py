"""Figure of one Navier–Stokes test sample: m₀, m_T, the true v₀ and the v₀ that trained
networks predict (the SIP paper's Fig. 7 panels), re-drawn from run directories.

    python docs/reproductions/sip_fluid_figure.py RUN_DIR [RUN_DIR ...] [--sample 0]
        [--out docs/reproductions/figures/sip_navier_stokes_sample.png]

Each RUN_DIR is a finished ``physgrad`` run (its ``params.eqx``) of
``navier_stokes``; its label is the run's method. Colour: |v|; arrows: v every 4th cell.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from physgrad.harness.config import RunConfig  # noqa: E402
from physgrad.harness.train import build, load_network  # noqa: E402


def velocity_panel(ax, v, dx, title, vmax):
    n = v.shape[-1]
    speed = np.sqrt(v[0] ** 2 + v[1] ** 2)
    ax.imshow(speed.T, origin="lower", extent=(0, n * dx, 0, n * dx), cmap="viridis", vmin=0, vmax=vmax)
    s = 4
    c = (np.arange(0, n, s) + 0.5) * dx
    ax.quiver(c[:, None].repeat(len(c), 1), c[None, :].repeat(len(c), 0), v[0, ::s, ::s], v[1, ::s, ::s],
              color="white", scale=vmax * 12, width=0.004)  # fmt: skip
    ax.set_title(title, fontsize=9)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--sample", type=int, default=0)
    parser.add_argument("--out", default="docs/reproductions/figures/sip_navier_stokes_sample.png")
    args = parser.parse_args()
    # the committed runs were trained by a command line that enabled x64 for its process
    # (before the harness scoped float64 as fit does): redraw them as they were computed
    jax.config.update("jax_enable_x64", True)
    first = Path(args.runs[0])
    setup = build(RunConfig.from_dict(json.loads((first / "config.json").read_text())))
    problem = setup.problem
    test = jax.tree.map(lambda a: a[args.sample], setup.data["test"])
    predictions = []
    for run in args.runs:
        config = json.loads((Path(run) / "config.json").read_text())
        network = load_network(run)
        x = np.asarray(problem.network_output(network, test))
        err = float(problem.metrics(x, None, test)["v0_l1"])
        predictions.append((f"{config['method']} (seed {config['seed']}): v0_l1 {err:.0f}", x))
    truth = np.asarray(test["v0"])
    vmax = float(np.sqrt((truth**2).sum(0)).max())
    n, dx = problem.resolution, problem.dx
    fig, axes = plt.subplots(1, 3 + len(predictions), figsize=(3 * (3 + len(predictions)), 3.2))
    for ax, name in zip(axes[:2], ("m0", "mT")):
        ax.imshow(np.asarray(test[name]).T, origin="lower", extent=(0, n * dx, 0, n * dx), cmap="magma")
        ax.set_title({"m0": "marker m₀", "mT": "marker m_T (target)"}[name], fontsize=9)
    velocity_panel(axes[2], truth, dx, "true v₀", vmax)
    for ax, (title, x) in zip(axes[3:], predictions):
        velocity_panel(ax, x, dx, title, vmax)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

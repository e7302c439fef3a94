"""Tables and figures of the long studies (docs/reproductions/long/studies.sh), from the
committed run directories alone.

Each study has one directory per method (its own step budget: the paper's wall-clock budget
divided by the method's time per step measured alone, calibration.csv). A curve is drawn
against the calibrated time axis t = step × (seconds per step measured alone) and, in a
second panel, against the run's raw training wall-clock (load-dependent: the studies ran on
one core beside other work). Runs still in progress (no summary, or a summary that did not
reach the budget) are drawn to their last evaluation and marked "partial" in the table and
in the figure (an open circle at their last evaluation, "(partial …)" in the legend); runs
with no evaluation after the first are left out of the figure. Studies of the stabilised-BPTT
paper are drawn smoothed as the paper's plots (a 30-epoch moving average), and a study may
ask for log–log axes (Poisson, as the authors plot it).

A tune lane (one ``physgrad tune`` directory per method) is read the same way: its chosen
configuration's runs (``METHOD/final``) are the curves, and the trial table of each method
follows once its trials have finished. A study with nothing evaluated yet (a lane that has
just started) gets no section and no figure: one line at the end names it.

    python docs/reproductions/long/report.py [STUDY ...]     # default: every study under data/
"""

from __future__ import annotations

import csv
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from physgrad.engine.recording import kept_path, read_metrics  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA = HERE.parent / "data"
FIGURES = HERE.parent / "figures"


@dataclass(frozen=True)
class Study:
    """How one study is read: its problem, the paper's minutes per run (a marker), the test
    metric, the method the others are divided by, the x-axis of the left panel
    (``calibrated``: step × seconds per step measured alone; ``steps``: equal-update budgets,
    the papers' own parity), the half-inverse route, and whether a run's value is its last
    evaluation (``tail=0``) or its mean over the last ``tail`` fraction of evaluations (the
    stabilised-BPTT protocol: the last 10 % of epochs). ``smooth``: the figure draws a moving
    average over this many evaluations, left-padded with the first value (the stabilised-BPTT
    paper's 30-epoch smoothing); ``logx``: log–log axes."""

    problem: str
    minutes: float | None = None
    metric: str = "loss"
    baseline: str = "adam"
    axis: str = "calibrated"
    route: str = "gram"
    tail: float = 0.0
    smooth: int = 0
    logx: bool = False
    # another study on the same problem whose runs are drawn and tabulated beside this
    # one's, cut at this study's calibrated budget (its last evaluation at or before it): a
    # short ablation measured against the long study's curves instead of re-running them
    reference: str | None = None


# the sub-directory of a `physgrad tune` output that holds the chosen configuration's runs
TUNED = "final"

STUDIES = {
    "oscillators_60min": Study("oscillators", 60),
    "quantum_dipole_90min": Study("quantum_dipole", 90),
    "quantum_dipole_screen": Study("quantum_dipole", axis="steps"),
    # the structured route (the oscillator and dipole studies ran before it existed)
    "poisson_hig_b64": Study("poisson_hig", route="structured", logx=True),
    "sip_navier_stokes": Study("navier_stokes", metric="v0_l1"),
    "sip_navier_stokes_ws": Study("navier_stokes", metric="v0_l1"),
    "quantum_control_1000ep": Study("quantum_control", baseline="bptt", axis="steps", tail=0.1, smooth=30),
    # B9: M and C under value and no clipping (the norm runs are quantum_control_1000ep)
    "quantum_control_1000ep_clip": Study(
        "quantum_control", baseline="sbptt_m-clipvalue", axis="steps", tail=0.1, smooth=30
    ),
    "guidance_1000ep": Study("guidance", baseline="bptt-clipnorm", axis="steps", tail=0.1, smooth=30),
    "ks_correction_2ep": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    "ks_correction_2ep_shuffled": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    "ks_correction_20ep": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    "ks_correction_2ep_grouped": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    "ks_prediction_2ep_grouped": Study("ks", metric="rel_error", baseline="wig", axis="steps"),
    "kolmogorov_16_2ep_correction": Study("kolmogorov", metric="rel_error", baseline="one", axis="steps"),
    "kolmogorov_16_2ep_prediction": Study("kolmogorov", metric="rel_error", baseline="one", axis="steps"),
    "kolmogorov_zero_init": Study("kolmogorov", metric="rel_error", baseline="nog", axis="steps"),
    "kolmogorov_zero_init_grouped": Study("kolmogorov", metric="rel_error", baseline="nog", axis="steps"),
    "ks_correction_20ep_grouped": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    "ks_prediction_20ep_grouped": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    "kolmogorov_32": Study("kolmogorov", metric="rel_error", baseline="one", axis="steps"),
    "sip_heat_10k": Study("heat", metric="x_l1_clamped", axis="steps"),
    "sip_poisson_10k": Study("poisson", metric="x_l1", axis="steps"),
    "sip_heat_10k_gpu": Study("heat", metric="x_l1_clamped", axis="steps"),
    "sip_poisson_10k_gpu": Study("poisson", metric="x_l1", axis="steps"),
    # one HIG run on a lent GPU, kept as one compare output (no method directories)
    "poisson_hig_b64_gpu": Study("poisson_hig", baseline="hig", axis="steps", route="structured", logx=True),
    # Kronecker-factored HIG's power ablation (−½, −¾, −1) against the long studies' HIG/Adam
    "khig_oscillators": Study("oscillators", baseline="hig", reference="oscillators_60min"),
    "khig_quantum_dipole": Study("quantum_dipole", baseline="hig", reference="quantum_dipole_90min"),
    # the blog's 80 KS epochs with a plateau schedule (lanes ks80, ks80_prediction)
    "ks_correction_80ep_plateau": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    "ks_prediction_80ep_plateau": Study("ks", metric="rel_error", baseline="one", axis="steps"),
    # H4 with every rule tuned (lanes dipole_tuned, dipole_tuned_90min): one `physgrad tune`
    # directory per method; its chosen configuration's seeds are the runs under METHOD/final,
    # at HIG's default (structured) route of the pinned physgrad
    "quantum_dipole_tuned_150s": Study("quantum_dipole", 2.5, baseline=f"adam/{TUNED}", route="auto (structured)"),
    "quantum_dipole_tuned_90min": Study("quantum_dipole", 90, baseline=f"adam/{TUNED}", route="auto (structured)"),
}


def on_gpu(study: Path) -> bool:
    """The studies run on a lent GPU machine are named ``…_gpu``; every other ran on one core."""
    return study.name.endswith("_gpu")


def study_of(name: str) -> Study:
    return STUDIES.get(name, Study(name))


# settings (as they appear in a directory name) that leave the work of one update unchanged
COST_NEUTRAL = ("lr", "learning_rate", "truncation", "eta", "power")


def method_of(directory: str) -> tuple[str, int | None, str | None]:
    """A method directory's (first method, switch step, second method): ``adam-1413-hig`` is
    Adam for 1,413 steps then HIG; ``hig-higlr01`` (a setting appended) is HIG."""
    parts = directory.split("-")
    if len(parts) == 3 and parts[1].isdigit():
        return parts[0], int(parts[1]), parts[2]
    return parts[0], None, None


def calibration() -> dict[tuple[str, str, str], float]:
    """(problem, method, route) -> seconds per step measured alone (route '' for the others)."""
    with (HERE / "calibration.csv").open() as f:
        return {(r["problem"], r["method"], r["route"]): float(r["ms_per_step"]) / 1e3 for r in csv.DictReader(f)}


def seconds(cal, study: str, method: str, step):
    """Calibrated time at ``step`` of a method directory: a sequence such as
    ``adam-1413-hig`` spends its first 1,413 steps at Adam's rate, the rest at HIG's; a
    directory with a changed setting keeps its method's calibration when the setting cannot
    change the work of an update (a learning rate ``hig-higlr01``, a truncation
    ``hig-higtruncation0001``); any other setting (a batch size) has none of its own (NaN)."""
    spec = study_of(study)
    method = method.removesuffix(f"/{TUNED}")  # a tune lane's chosen configuration: its method's rate

    def rate(m):
        return cal.get((spec.problem, m, spec.route if m in ("gn", "hig") else ""), math.nan)

    first, n, second = method_of(method)
    step = np.asarray(step, float)
    if n is not None:
        return np.minimum(step, n) * rate(first) + np.maximum(step - n, 0) * rate(second)
    setting = method[len(first) + 1 :].removeprefix(first)
    same_work = first == method or setting.startswith(COST_NEUTRAL)
    return step * (rate(first) if same_work else math.nan)


def runs(study: Path, method: str) -> list[dict]:
    """Every run of one method: seed, test-metric curve (step, wall), status and budget."""
    metric = study_of(study.name).metric
    out = []
    for run in sorted((study / method / "runs").glob("*-seed*")):
        metrics = run / "metrics.csv"  # or its copy packed by prune.py --pack
        if not kept_path(metrics).exists():
            continue
        rows = [r for r in read_metrics(metrics) if r["split"] == "test" and r["metric"] == metric]
        summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else None
        config = json.loads((run / "config.json").read_text())
        out.append({
            "seed": config["seed"], "method": config["method"], "budget": config["budget"]["steps"],
            "step": np.array([int(r["step"]) for r in rows]), "wall": np.array([float(r["wall_time"]) for r in rows]),
            "loss": np.array([float(r["value"]) for r in rows]),
            "t": seconds(calibration(), study.name, method, [int(r["step"]) for r in rows]),
            "status": summary["status"] if summary else "partial",
            "partial": summary is None or (summary["status"] != "diverged" and summary["steps"] < config["budget"]["steps"]),
            "last_step": (summary.get("diverged_step") or summary["steps"]) if summary else (int(rows[-1]["step"]) if rows else 0),
        })  # fmt: skip
    return out


def final_value(run: dict, tail: float) -> float:
    """The run's last evaluation, or its mean over the last ``tail`` fraction of evaluations."""
    if not tail:
        return run["loss"][-1]
    return float(np.mean(run["loss"][-max(1, int(round(tail * (len(run["loss"]) - 1)))) :]))


def cut(run: dict, limit: float) -> dict:
    """A reference run read up to the calibrated time ``limit`` (s): its evaluations at or
    before it, finished there if it got that far."""
    keep = np.asarray(run["t"]) <= limit * (1 + 1e-9)
    reached = bool(keep.any()) and (run["status"] == "finished" or run["t"][keep][-1] < run["t"][-1])
    out = {**run, **{k: np.asarray(run[k])[keep] for k in ("step", "wall", "loss", "t")}}
    if reached and run["status"] != "diverged":
        last = int(out["step"][-1]) if len(out["step"]) else 0
        out.update(status="finished", partial=False, last_step=last, budget=last)
    return out


def with_reference(study: Path, data: dict) -> dict:
    """``data`` plus the reference study's runs, cut at this study's longest calibrated
    budget, under the names ``METHOD (REFERENCE)``."""
    spec = study_of(study.name)
    if spec.reference is None:
        return data
    limit = max((float(seconds(calibration(), study.name, m, r["budget"])) for m, rs in data.items() for r in rs),
                default=0.0)  # fmt: skip
    reference = DATA / spec.reference
    out = dict(data)
    for m in sorted(p.name for p in reference.iterdir() if (p / "runs").is_dir()):
        rs = [cut(r, limit) for r in runs(reference, m)]
        if rs and not math.isnan(float(seconds(calibration(), spec.reference, m, 1))):
            out[f"{m} ({spec.reference})"] = rs
    return out


TOP = "(top level)"  # the label's suffix of a study's top-level runs whose method has a directory too


def table(study: Path, cal) -> tuple[list[str], dict]:
    spec = study_of(study.name)
    # a method directory may be nested: a setting with a '/' (curriculum=1/2/4) made one
    own = sorted(p.parent.relative_to(study).as_posix() for p in study.rglob("runs")
                 if p.is_dir() and "runs" not in p.parent.relative_to(study).parts)  # fmt: skip
    data = with_reference(study, {m: runs(study, m) for m in own})
    if "." in data:  # the study directory is itself a compare output: one row per method
        own.remove(".")
        top = {}
        for r in data.pop("."):  # a method that also has its own directory keeps both apart
            top.setdefault(r["method"] if r["method"] not in own else f"{r['method']} {TOP}", []).append(r)
        data.update(top)
        own += sorted(top)
    methods = sorted(data)
    finals = {}
    value = f"final test {spec.metric}" + (f" (mean of the last {spec.tail:.0%} of evaluations)" if spec.tail else "")
    lines = [f"| method | s/step alone | budget (steps) | runs | {value}: mean ± std | per seed | / {spec.baseline} | state |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for m in methods:
        rs = data[m]
        done = [r for r in rs if r["status"] == "finished"]
        div = [r for r in rs if r["status"] == "diverged"]
        values = np.array([final_value(r, spec.tail) for r in done if len(r["loss"])])
        finals[m] = values
        state = ", ".join(f"seed {r['seed']}: {r['status']} at step {r['last_step']}"
                          for r in rs if r["status"] != "finished") or "all finished"  # fmt: skip
        mean = f"{values.mean():.3e} ± {values.std(ddof=1) if len(values) > 1 else 0:.1e}" if len(values) else "-"
        # each seed's own value: with 3 seeds the spread between them is the evidence, and
        # the docs' per-seed ratios are read from here
        seeds = " / ".join(f"{r['seed']}: " + (f"{final_value(r, spec.tail):.3g}" if r["status"] == "finished" and len(r["loss"])
                                               else r["status"]) for r in sorted(rs, key=lambda r: r["seed"])) or "-"  # fmt: skip
        name, source = (
            (m.split(" (")[0], spec.reference or study.name)
            if m not in own
            else (m.removesuffix(f" {TOP}"), study.name)
        )
        # calibration.csv holds one CPU core's step times: none applies to a run on a GPU
        cpu = method_of(name)[1] is None and not on_gpu(study)
        per_step = float(seconds(cal, source, name, 1)) if cpu else math.nan
        lines.append(f"| {m} | {per_step:.4f} | {rs[0]['budget'] if rs else '-'} | "
                     f"{len(done)} finished, {len(div)} diverged | {mean} | {seeds} | RATIO_{methods.index(m)}_ | {state} |")  # fmt: skip
    base = finals.get(spec.baseline, finals.get(f"{spec.baseline} ({spec.reference})"))
    for i, line in enumerate(lines):
        for m in methods:
            if f"RATIO_{methods.index(m)}_" in line:
                ratio = (
                    f"{finals[m].mean() / base.mean():.3g}"
                    if base is not None and len(base) and len(finals[m])
                    else "-"
                )
                lines[i] = line.replace(f"RATIO_{methods.index(m)}_", ratio)
    return lines, data


def smoothed(values: np.ndarray, window: int) -> np.ndarray:
    """Moving average over ``window`` values, left-padded with the first value (the
    stabilised-BPTT paper's smoothing of its curves); ``window`` 0 or 1: unchanged."""
    if window <= 1 or not len(values):
        return values
    padded = np.concatenate([np.full(window - 1, values[0]), values])
    return np.convolve(padded, np.ones(window) / window, mode="valid")


def figure(study: Path, data: dict, cal, out: Path):
    spec = study_of(study.name)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    # one colour per method and one line style per seed: a study can hold more runs than a
    # colour cycle has colours, and two methods must never share one
    colours = plt.get_cmap("tab10" if len(data) <= 10 else "tab20")
    dashes = ["-", "--", ":", "-."]
    any_partial = False
    for k, (m, rs) in enumerate(sorted(data.items())):
        for r in rs:
            if not drawable(r):  # nothing evaluated after the first evaluation
                continue
            t = np.asarray(r["t"], float) / 60 if spec.axis == "calibrated" else r["step"]
            label = f"{m} seed {r['seed']}" + (" (diverged)" if r["status"] == "diverged" else "")
            if r["partial"]:
                label += f" (partial: step {r['last_step']:,} of {r['budget']:,})"
                any_partial = True
            alpha = 0.45 if r["partial"] else 0.8
            style = dict(alpha=alpha, lw=1, color=colours(k), ls=dashes[int(r["seed"]) % len(dashes)], label=label)
            y = smoothed(r["loss"], spec.smooth)
            for ax, x in ((axes[0], np.asarray(t, float)), (axes[1], r["wall"] / 60)):
                keep = x > 0 if spec.logx else np.ones(len(x), bool)  # a log axis has no t = 0
                ax.semilogy(x[keep], y[keep], **style)
                if r["partial"] and keep.any():
                    ax.plot(x[keep][-1], y[keep][-1], "o", mfc="none", mec=colours(k), ms=6)
    for ax in axes if spec.logx else ():
        ax.set_xscale("log")
    axes[0].set_xlabel("calibrated time (min): step × s/step measured alone" if spec.axis == "calibrated" else "update")
    where = "on a lent GPU" if on_gpu(study) else "one core under load"
    axes[1].set_xlabel(f"raw training wall-clock (min, {where})")
    axes[0].set_ylabel(f"test {spec.metric}" + (f" ({spec.smooth}-epoch moving average)" if spec.smooth else ""))
    if spec.minutes and spec.axis == "calibrated":
        axes[0].axvline(spec.minutes, color="k", ls=":", lw=1)
    axes[0].legend(fontsize=7)
    notes = [f"smoothed over {spec.smooth} epochs as the paper" if spec.smooth else "",
             "open circle: a partial run's last evaluation" if any_partial else ""]  # fmt: skip
    note = "; ".join(n for n in notes if n)
    title = f"{spec.problem}: long study ({study.name})"
    if note:
        fig.suptitle(f"{title}\n{note}", fontsize=10)
    else:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(names: list[str]):
    if {"-h", "--help"} & set(names):
        print(__doc__ or "usage: python docs/reproductions/long/report.py [STUDY ...]")
        return
    kept = sorted(p.name for p in DATA.iterdir() if p.is_dir() and p.name != "short")
    unknown = [n for n in names if n not in kept]
    if unknown:  # one line, exit 2, as the physgrad command line answers a wrong name
        print(f"report.py: no study {unknown[0]!r} under {DATA}; choose from: {', '.join(kept)}", file=sys.stderr)
        raise SystemExit(2)
    studies = [DATA / n for n in (names or kept)]
    cal = calibration()
    waiting = []
    for study in studies:
        lines, data = table(study, cal)
        tuning = tune_tables(study)
        drawn = any(drawable(r) for rs in data.values() for r in rs)
        if not drawn and not tuning:  # a lane that has not evaluated anything yet: no section
            waiting.append(study.name)
            continue
        print(f"### {study.name}\n")
        if data:
            print("\n".join(lines))
        for text in tuning:
            print(f"\n{text}")
        if drawn:  # a figure with no curve would say nothing (and leave a new file behind)
            out = FIGURES / f"long_{study.name}.png"
            figure(study, data, cal, out)
            print(f"\n![{study.name}](figures/{out.name})\n")
        else:
            print()
    if waiting:
        print(f"Not drawn yet, no evaluation kept (their lanes in long/studies.sh add them): {', '.join(waiting)}")


def drawable(run: dict) -> bool:
    """A run the figure draws: evaluated after its first evaluation, or diverged (its one
    point is kept, and its label says that it diverged)."""
    return len(run["loss"]) >= 2 or (len(run["loss"]) == 1 and run["status"] == "diverged")


def tune_tables(study: Path) -> list[str]:
    """The trial table of each ``physgrad tune`` directory in ``study`` (one per method, a
    tune lane's layout) whose trials have all finished (``trials.csv`` is written then), as
    ``physgrad report DIR`` prints it, without its figure: redrawing would write into the
    kept data."""
    dirs = [d for d in sorted(study.iterdir()) if (d / "tune.json").exists() and kept_path(d / "trials.csv").exists()]
    if not dirs:
        return []
    from physgrad.harness.tune_report import table as tune_table  # only a tune lane needs the harness

    out = []
    for d in dirs:
        rows = tune_table(d)
        lines = [f"Tuning trials, `{d.relative_to(study).as_posix()}` (validation loss; the chosen configuration's "
                 f"runs are `{d.name}/{TUNED}` above):", "", "| " + " | ".join(rows[0]) + " |",
                 "|" + "---|" * len(rows[0])] + ["| " + " | ".join(r) + " |" for r in rows[1:]]  # fmt: skip
        out.append("\n".join(lines))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])

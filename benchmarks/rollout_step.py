"""Time and peak memory per update of R, M, S and C (one-pass and two-pass) on the
stabilised-BPTT problems, and C's cost relative to R.

StableBPTT's C needs the gradients of two policies. The authors run two full forward +
backward passes (about 2× BPTT); physgrad's one-pass C runs one forward rollout and one
backward scan carrying both adjoints, linearising each step once. This prints, per problem,
each variant's median time per training step (the engine's jitted step: gradient, clipping,
Adam), its temporary memory as compiled by XLA, and the ratio to R measured in the same
run; the forward rollout alone is the cost floor. ``--checkpoint`` rematerialises the scan.

    python benchmarks/rollout_step.py [--problems cartpole,guidance,quantum_control]
                                      [--batch-size 8] [--repeats 30] [--checkpoint] [--set name=value ...]
"""

from __future__ import annotations

import platform

import jax
from common import benchmark_parser, median_seconds, settings_from, training_step

from physgrad.rollout import rollout

VARIANTS = [
    ("R", "bptt", {}),
    ("M", "sbptt_m", {}),
    ("S", "no_temporal", {}),
    ("C one-pass", "sbptt_c", {"one_pass": "true"}),
    ("C two-pass", "sbptt_c", {"one_pass": "false"}),
]


def temp_bytes(fn, args) -> float:
    """XLA's temporary buffer size of the compiled function (its peak scratch memory)."""
    analysis = fn.lower(*args).compile().memory_analysis()
    return float(getattr(analysis, "temp_size_in_bytes", float("nan")))


def main():
    parser = benchmark_parser(__doc__.splitlines()[0], "cartpole")
    parser.add_argument("--problems", default="cartpole,guidance,quantum_control")
    parser.add_argument("--checkpoint", action="store_true", help="two-level rematerialisation of the rollout scan")
    args = parser.parse_args()
    settings = settings_from(args)
    if args.checkpoint:
        settings["checkpoint"] = "true"
    print(f"median seconds per update, {args.repeats} repeats, checkpoint={args.checkpoint} "
          f"({platform.processor() or platform.machine()}, {jax.devices()[0].platform}, jax {jax.__version__})")  # fmt: skip
    for problem in args.problems.split(","):
        rows = []
        for label, method, extra in VARIANTS:
            config, setup, step, step_args = training_step(problem, method, {**settings, **extra})
            rows.append((label, median_seconds(step, step_args, args.repeats), temp_bytes(step, step_args)))
        batch = config.phases[0].batch_size
        s0 = setup.data["train"][:batch]
        forward = jax.jit(lambda p: rollout(setup.objective.rollout, p, s0)[0])
        floor = median_seconds(forward, (setup.params,), args.repeats)
        r_time, r_mem = rows[0][1], rows[0][2]
        print(
            f"\n{problem} (batch {batch}, {setup.objective.rollout.num_steps} steps): forward rollout alone {1e3 * floor:.3f} ms"
        )
        print(f"{'variant':<12} {'ms/update':>10} {'/ R':>6} {'/ forward':>10} {'temp MiB':>9} {'mem / R':>8}")
        for label, t, mem in rows:
            print(
                f"{label:<12} {1e3 * t:>10.3f} {t / r_time:>6.2f} {t / floor:>10.2f} {mem / 2**20:>9.3f} {mem / r_mem:>8.2f}"
            )


if __name__ == "__main__":
    main()

"""Time per update of the time-stepper modalities (ONE, NOG, WIG) against the forward rollout
alone, in the prediction and correction setups, and PRDP's lever: WIG's cost against the
solver's iteration count.

The floor is the stepper's m-step forward rollout on the same batch (no gradient); each
modality's jitted training step (gradient, skip checks, Adam) is reported in milliseconds
and as a multiple of that floor, measured in the same run. ``--iterations`` times WIG on
``advection_1d``'s implicit-upwind corrector at several Jacobi sweep counts.

    python benchmarks/unrolling_step.py [--problem ks] [--repeats 30] [--set name=value ...]
                                        [--iterations 1,5,20]
"""

from __future__ import annotations

import platform

import jax
from common import benchmark_parser, median_seconds, settings_from, training_step

from physgrad.rollout import rollout


def main():
    parser = benchmark_parser(__doc__.splitlines()[0], "ks")
    parser.add_argument("--iterations", default="1,2,5,10,20", help="Jacobi sweeps for the PRDP timing ('' to skip)")
    args = parser.parse_args()
    print(f"# {platform.processor() or platform.machine()}, {jax.default_backend()}, {jax.device_count()} device(s)")
    for setup_name in ("prediction", "correction"):
        settings = {**settings_from(args), "setup": setup_name}
        floor = None
        for method in ("one", "nog", "wig"):
            config, setup, step, step_args = training_step(args.problem, method, settings)
            if floor is None:
                system = setup.objective.unrolled(None, False)
                batch = jax.tree.map(lambda a: a[: config.phases[0].batch_size], setup.data["train"])
                forward = jax.jit(lambda p, b: rollout(system, p, system.initial_state(b))[0])
                floor = median_seconds(forward, (setup.params, batch), args.repeats)
                print(f"{args.problem} {setup_name}: forward rollout (m = {system.num_steps}, batch "
                      f"{config.phases[0].batch_size}) {1e3 * floor:.2f} ms")  # fmt: skip
            t = median_seconds(step, step_args, args.repeats)
            print(f"  {method:4s} {1e3 * t:8.2f} ms/update  {t / floor:5.2f}x the forward rollout")
    if args.iterations:
        print("advection_1d correction, wig: time per update against the solver's Jacobi sweeps")
        base = None
        for k in args.iterations.split(","):
            _, _, step, step_args = training_step("advection_1d", "wig", {"setup": "correction", "iterations": k})
            t = median_seconds(step, step_args, max(args.repeats, 100))
            base = base or t
            print(f"  K = {k:>3s}: {1e3 * t:7.3f} ms/update  {t / base:5.2f}x K = {args.iterations.split(',')[0]}")


if __name__ == "__main__":
    main()

"""PhiFlow as a simulator source (:mod:`physgrad.problems.sim.phiflow`) against the pure-JAX fluid.

What is compared, and why the tolerances are what they are (measured on 8×8 to 16×16 grids,
dx = 2, dt = 0.25, 1 to 8 steps, float32):

- PhiFlow 3.4's ``advect.mac_cormack`` clamps each *staggered* velocity component to the
  2 × 2 values around the back-traced point as if the component were cell centred (its
  ``Field.closest_values`` ignores the face offset: the limiter's neighbourhood is shifted
  half a cell along the component's own axis), while :func:`physgrad.problems.sim.fluid.mac_cormack` uses
  the component's own faces. Where the limiter bites, the two differ by up to ~5 % of the
  velocity after one step; after 8 steps |Δv| reaches 0.44 of max |v| ≈ 2 and the marker
  0.06 (gradients ~25 % apart). The marker advection (cell centred), the projection and
  the energy rescale agree to float32 rounding.
- ``fluid.rollout(..., limiter="cells")`` is physgrad's fluid with PhiFlow's limiter. Against it the PhiFlow rollout agrees to ≤ 4e-5 in the
  states and ≤ 3e-4 relative in the gradients (this test: 8×8, 2 steps; 16×16, 8 steps:
  states 2.3e-5), whether the JAX side projects exactly (FFT) or by CG at 1e-4 (lineax,
  max-norm residual; PhiML stops on the L2 residual of a Lagrange-augmented system, so the
  two CGs stop at different iterates — below 2e-5 here because both solve far past 1e-4
  on these small grids). What remains is float32 rounding through bilinear sampling,
  clamping and the energy rescale. Tolerances: states 1e-4 absolute (values O(1)),
  gradients 1e-3 of max |g|.
- ``physgrad.problems.sim.fluid.rollout`` differs from PhiFlow by the limiter alone: the difference
  PhiFlow − fluid equals reference − fluid to the same 1e-4.

PhiFlow is slow to trace and XLA slow to compile these graphs on one core, so everything
runs on an 8 × 8 grid, 2 steps, 2 samples, each computation compiled once (module fixtures).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad import jacobian
from physgrad.inverse import GaussNewton
from physgrad.problems.sim import fluid, phiflow

# The PhiFlow comparisons trace PhiFlow and compile its graphs in a fresh interpreter (about a
# minute of CPU from a cold cache): the slow tier, which CI runs after make test.
pytestmark = pytest.mark.slow

# A spec check, not pytest.importorskip("phi"): collecting this module imports no PhiFlow
# (physgrad.problems.sim.phiflow imports it on first use, which the tests below exercise).
if not phiflow.phiflow_available():
    pytest.skip("PhiFlow is not installed (pip install physgrad[phiflow])", allow_module_level=True)

DX = 2.0  # cell size in the tests of the adapter alone

# The README's "PhiFlow simulators" example: the README's own block once the section exists,
# else this copy of it (test_readme_example and the comparisons run it verbatim).
README_EXAMPLE = """
import jax
import jax.numpy as jnp
from physgrad.problems.sim import fluid, phiflow

n, dx, dt, steps = 8, 2.0, 0.25, 2  # the SIP paper's fluid: 64 x 64 cells, dx = 2, dt = 0.25, 8 steps
keys = jax.random.split(jax.random.PRNGKey(0), 3)
velocity = jax.vmap(lambda k: fluid.project(jax.random.normal(k, (2, n, n)), dx)[0])(keys[:2])  # divergence free
marker = jax.random.uniform(keys[2], (2, n, n))  # a batch of 2 samples
target = jnp.roll(marker, 1, axis=1)


def loss(velocity, marker, target):  # one sample: velocity (2, n, n) staggered, marker (n, n)
    states = phiflow.rollout(marker, velocity, steps, dt, dx)  # fluid.rollout's call: (marker, velocity, markers)
    return jnp.sum((states[0] - target) ** 2), states


# per-sample losses, final states and gradients, in one pass (reverse mode only: no jax.jacfwd)
(losses, states), grads = jax.jit(jax.vmap(jax.value_and_grad(loss, has_aux=True)))(velocity, marker, target)
"""


def readme_example() -> str:
    readme = Path(__file__).parents[1] / "README.md"
    found = (
        re.search(r"## PhiFlow simulators.*?```python\n(.*?)```", readme.read_text(), re.S) if readme.exists() else None
    )
    return found.group(1) if found else README_EXAMPLE


def jax_rollouts(steps, dt, dx):
    """The JAX fluids compared with PhiFlow: ``name -> rollout(marker, velocity)``."""
    return {
        "reference_cg": lambda m, v: fluid.rollout(m, v, steps, dt, dx, fluid.CGProjection(1e-4), limiter="cells"),
        "reference_fft": lambda m, v: fluid.rollout(m, v, steps, dt, dx, limiter="cells"),
        "fluid": lambda m, v: fluid.rollout(m, v, steps, dt, dx),
    }


FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}  # tests only


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """One fresh interpreter with JAX's defaults (x64 off, as a user's), XLA at -O0 (these
    graphs take 30 s to compile at -O2 on one core). It checks that importing physgrad and
    physgrad.problems.sim.phiflow imports no PhiFlow and that a missing PhiFlow is one ImportError naming
    the extra; runs the README example verbatim (jit, vmap and grad through PhiFlow: losses,
    states and gradients); and records JAX's flags and PhiML's global settings
    before and after. Returns (the record, the arrays)."""
    folder = tmp_path_factory.mktemp("phiflow")
    (folder / "readme_example.py").write_text(readme_example())
    code = textwrap.dedent(
        f"""
        import json, sys
        import numpy as np
        import jax, jax.numpy as jnp
        import physgrad, physgrad.problems.sim.phiflow as pf
        out = {{"phi_imported_by_physgrad": "phi" in sys.modules or "phiml" in sys.modules}}
        sys.modules["phi"] = None  # PhiFlow missing
        try:
            pf.import_phiflow()
        except ImportError as error:
            out["missing"] = str(error)
        del sys.modules["phi"]
        flags = dict(jax.config.values)
        with jax.enable_x64(True):  # the first import inside a float64 scope (SIP's precision="float64")
            pf.import_phiflow()
        import phiml.backend as pb
        backend, precision = pb.default_backend(), pb.get_precision()
        ns = {{}}
        exec(open({str(folder / "readme_example.py")!r}).read(), ns)
        states = ns["states"]
        out["x64"] = jax.config.jax_enable_x64
        out["changed_flags"] = sorted(k for k, v in jax.config.values.items() if flags.get(k) != v)
        out["backend_restored"] = pb.default_backend() is backend
        out["precision"] = [precision, pb.get_precision()]
        out["dtypes"] = [str(ns["grads"].dtype)] + [str(a.dtype) for a in states]
        out["settings"] = [ns["n"], ns["dx"], ns["dt"], ns["steps"]]
        arrays = {{k: np.asarray(ns[k]) for k in ("velocity", "marker", "target", "grads")}}
        arrays.update(final_marker=np.asarray(states[0]), final_velocity=np.asarray(states[1]), markers=np.asarray(states[2]))
        np.savez({str(folder / "arrays.npz")!r}, **arrays)
        print(json.dumps(out))
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["XLA_FLAGS"] = " ".join([env.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0",
                                 "--xla_llvm_disable_expensive_passes=true"]).strip()  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-4000:]
    with np.load(folder / "arrays.npz") as data:
        arrays = {k: jnp.asarray(data[k]) for k in data.files}
    return json.loads(result.stdout.strip().splitlines()[-1]), arrays


@pytest.fixture(scope="module")
def phiflow_states(fresh):
    arrays = fresh[1]
    return arrays["final_marker"], arrays["final_velocity"], arrays["markers"]


@pytest.fixture(scope="module")
def references(fresh):
    """States and gradients of the README's loss for every JAX rollout (one compilation)."""
    record, arrays = fresh
    _, dx, dt, steps = record["settings"]

    def all_rollouts(marker, velocity, target):
        out = {}
        for name, rollout in jax_rollouts(steps, dt, dx).items():

            def loss(v):
                states = rollout(marker, v)
                return jnp.sum((states[0] - target) ** 2), states

            grad, states = jax.grad(loss, has_aux=True)(velocity)
            out[name] = (states, grad)
        return out

    args = (arrays["marker"], arrays["velocity"], arrays["target"])
    return jax.jit(jax.vmap(all_rollouts)).lower(*args).compile(FAST_COMPILE)(*args)


def max_abs(a, b):
    return float(jnp.max(jnp.abs(jnp.asarray(a) - jnp.asarray(b))))


# --- (a) PhiFlow against the JAX fluid ----------------------------------------------------------
@pytest.mark.parametrize("name", ["reference_cg", "reference_fft"])
def test_phiflow_states_equal_the_jax_fluid_with_phiflows_limiter(phiflow_states, references, name):
    states, _ = references[name]
    for got, want in zip(phiflow_states, states):  # final marker, final velocity, markers per step
        assert got.shape == want.shape and got.dtype == jnp.float32
        assert max_abs(got, want) < 1e-4


@pytest.mark.parametrize("name", ["reference_cg", "reference_fft"])
def test_phiflow_gradients_equal_the_jax_fluid_with_phiflows_limiter(fresh, references, name):
    _, grads = references[name]
    scale = float(jnp.max(jnp.abs(grads)))
    assert scale > 1e-2  # a real gradient
    assert max_abs(fresh[1]["grads"], grads) < 1e-3 * scale


def test_fluid_rollout_differs_from_phiflow_by_the_limiter_alone(phiflow_states, fresh, references):
    (fluid_states, fluid_grads), (ref_states, ref_grads) = references["fluid"], references["reference_cg"]
    for got, ref, base in zip(phiflow_states, ref_states, fluid_states):
        assert max_abs(got - base, ref - base) < 1e-4
    scale = float(jnp.max(jnp.abs(fluid_grads)))
    assert max_abs(fresh[1]["grads"] - fluid_grads, ref_grads - fluid_grads) < 1e-3 * scale


def test_readme_example(fresh):
    """The README example ran verbatim (jit, vmap and grad through PhiFlow) in a user's
    setting (x64 off): float32 throughout, finite, nonzero gradients (compared above)."""
    record, arrays = fresh
    assert record["dtypes"] == ["float32"] * 4
    grads, n = arrays["grads"], record["settings"][0]
    assert grads.shape == (2, 2, n, n)
    assert bool(jnp.all(jnp.isfinite(grads))) and float(jnp.max(jnp.abs(grads))) > 0


# --- the adapter ------------------------------------------------------------------------------
def test_layout_is_physgrads_lower_faces():
    """PhiFlow's periodic staggered x-values sit at (iΔx, (j+½)Δx), as fluid.py's."""
    domain = phiflow.Domain((4, 4), DX)
    points = phiflow.wrap(lambda v: v.points, domain, [phiflow.Staggered()], phiflow.Plain())(jnp.zeros((2, 4, 4)))
    # PhiML order: (~vector: the component, x, y, vector: the coordinate)
    for component in range(2):
        want = fluid.sample_points(4, DX, fluid.STAGGERED[component])
        np.testing.assert_allclose(np.moveaxis(np.asarray(points[component]), -1, 0), want, atol=1e-5)
    ramp = jnp.arange(32.0).reshape(2, 4, 4)
    back = phiflow.wrap(lambda v: v, domain, [phiflow.Staggered()], phiflow.Staggered())(ramp)
    np.testing.assert_array_equal(back, ramp)


def test_wrapped_functions_are_reverse_only_and_gauss_newton_sees_it():
    assert jacobian.is_reverse_only(phiflow.rollout) and jacobian.is_reverse_only(phiflow.step)
    double = phiflow.wrap(lambda c: c * 2.0, phiflow.Domain((4, 4), DX), [phiflow.Centered()], phiflow.Centered())
    assert jacobian.is_reverse_only(double)

    def forward(x_flat):  # a problem's closure: no mark to see, the JVP probe decides
        return double(x_flat.reshape(4, 4)).ravel()

    x = jnp.arange(16.0)
    assert not jacobian.supports_forward_mode(forward, x)
    assert jacobian.jacobian_mode(forward, x, output_size=16) == "reverse"
    result = GaussNewton(1e-6)(lambda x, s: forward(x), x, forward(x), forward(x) + 2.0, None)  # J = 2 I
    np.testing.assert_allclose(result.x, x + 1.0, rtol=1e-6)


@pytest.mark.filterwarnings("ignore:Rank deficiency")  # PhiFlow's own, on every periodic projection
def test_a_default_solve_is_refused_in_one_line():
    flow = phiflow.import_phiflow()
    project = phiflow.wrap(
        lambda v: flow.fluid.make_incompressible(v)[0],
        phiflow.Domain((4, 4), DX),
        [phiflow.Staggered()],
        phiflow.Staggered(),
    )
    with pytest.raises(ValueError, match=r"^a PhiFlow solve ran with method 'scipy-direct'.*Solve\('CG'") as info:
        jax.eval_shape(project, jnp.zeros((2, 4, 4)))
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="unknown array kind"):
        phiflow.wrap(lambda c: c, phiflow.Domain((4, 4), DX), ["cell"], phiflow.Centered())


@pytest.mark.unchecked("the deprecated strings are passed on purpose")
def test_the_strings_of_0_1_0_are_their_objects_with_a_warning():
    """``"centered"``, ``"staggered"``, ``"vector"``, ``"array"`` and ``boundary="zero"`` (and
    the other boundaries) still work for one release, each as its object."""
    with pytest.warns(DeprecationWarning, match=r"kind='centered' is deprecated; pass .*Centered\(\)"):
        double = phiflow.wrap(lambda c: c * 2.0, phiflow.Domain((4, 4), DX), ["centered"], "centered")
    assert double.inputs == (phiflow.Centered(),) and double.outputs == phiflow.Centered()
    for spelling, kind in phiflow.KINDS.items():
        with pytest.warns(DeprecationWarning, match=spelling):
            function = phiflow.PhiFlowFunction(lambda a: a, phiflow.Domain((4,), DX), (spelling,), (spelling,))  # type: ignore[arg-type]
            assert function.inputs == (kind,) and function.outputs == (kind,)
    for spelling, boundary in phiflow.BOUNDARIES.items():
        with pytest.warns(DeprecationWarning, match=f"boundary='{spelling}'") as warned:
            assert phiflow.Domain((4, 4), DX, spelling) == phiflow.Domain((4, 4), DX, boundary)  # type: ignore[arg-type]
        assert warned[0].filename == __file__  # the user's line, past Equinox's __post_init__ frames
    with pytest.raises(ValueError, match="unknown boundary 'wall'"):
        phiflow.Domain((4, 4), DX, "wall")  # type: ignore[arg-type]
    centred = phiflow.Domain((4, 4), DX, phiflow.Zero())
    with pytest.raises(ValueError, match="periodic domains only"):
        phiflow.wrap(lambda v: v, centred, [phiflow.Staggered()], phiflow.Staggered())(jnp.zeros((2, 4, 4)))


# --- (b) the process's configuration ---------------------------------------------------------------
def test_importing_and_using_phiflow_leaves_the_configuration_alone(fresh):
    """physgrad and physgrad.problems.sim.phiflow import no PhiFlow; a missing PhiFlow is one ImportError
    naming the extra; after the adapter imported PhiFlow (inside a jax.enable_x64 scope, as
    SIP's float64 inverse would) and ran it, x64 is still off, no JAX flag changed, and
    PhiML's default backend and precision are what they were."""
    record, _ = fresh
    assert record["phi_imported_by_physgrad"] is False
    assert "pip install physgrad[phiflow]" in record["missing"] and "\n" not in record["missing"]
    assert record["x64"] is False and record["changed_flags"] == []
    assert record["backend_restored"] and record["precision"] == [32, 32]

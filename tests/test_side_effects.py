"""Importing physgrad changes nothing in JAX's configuration (nor the environment or a thread
pool), and physgrad works with x64 off.

The test session itself runs with x64 on (conftest.py), so the x64-off side runs in fresh
interpreters (``sys.executable``, no conftest): they import this module and call the same
functions as the test process, so both sides compute the same thing. What is checked:

* every physgrad module imports without touching JAX's configuration, an environment
  variable or the size of a BLAS/LAPACK thread pool;
* the half-inverse (Gram, block-Gram, Lanczos, jitted), L-BFGS and one HIG training step
  of the oscillators give the same arrays with x64 off as with x64 on (the update physgrad
  always computed), and the Gram route equals a NumPy float64 SVD formula;
* float32 problems build the same float32 data and networks either way, bit for bit;
* a float64 problem says in one line that it needs x64.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from physgrad import problems
from physgrad.inverse import LBFGS
from physgrad.precision import cast_like, float64_scope, to_float64
from physgrad.routes import Gram, blockgram_half_inverse, half_inverse, lanczos_half_inverse

HERE = Path(__file__).parent


def run_fresh(code: str, tmp_path: Path) -> dict:
    """Run ``code`` in a fresh interpreter with JAX's defaults (x64 off) and return the JSON
    object it prints on its last line. The module under test is importable there."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PHYSGRAD_CACHE"] = str(tmp_path / "cache")  # generated data: never a cache from x64 runs
    prelude = f"import sys; sys.path.insert(0, {str(HERE)!r})\n"
    result = subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True, text=True, env=env, timeout=900
    )
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def save_in_fresh(function: str, tmp_path: Path) -> dict[str, np.ndarray]:
    """The arrays ``function()`` of this module returns, computed in a fresh x64-off interpreter."""
    out = tmp_path / f"{function}.npz"
    info = run_fresh(
        f"""
        import json, jax, numpy as np
        import test_side_effects as t
        arrays = t.{function}()
        np.savez({str(out)!r}, **arrays)
        print(json.dumps({{"x64": bool(jax.config.jax_enable_x64)}}))
        """,
        tmp_path,
    )
    assert info["x64"] is False  # nothing switched x64 on for good along the way
    with np.load(out) as f:
        return {k: f[k] for k in f.files}


# --- (a) imports, lazy imports and figures ------------------------------------------------
# One fresh interpreter for the three tests of a fresh import (each start costs ~3 s of CPU), in
# the order a notebook meets them: a backend of its own (svg) set first; JAX's configuration, the
# environment and the thread pools taken before physgrad is imported; the heavy optional packages
# looked for after importing physgrad and its command line; the figures drawn; then every
# physgrad module imported and the configuration, environment and pools compared.
FRESH_IMPORTS = """
import importlib, json, os, pkgutil, sys
import matplotlib
matplotlib.use("svg")
import equinox as eqx, jax, jax.numpy as jnp
import scipy.linalg.cython_lapack  # the LAPACK jaxlib runs on: its thread pool is loaded
from threadpoolctl import threadpool_info
before = {k: repr(v) for k, v in jax.config.values.items()}
environ = dict(os.environ)
pools = {p["filepath"]: p["num_threads"] for p in threadpool_info()}

import physgrad, physgrad.harness.cli, physgrad.harness.registry, physgrad.harness.study, physgrad.harness.bench
heavy = ("optimistix", "kfac_jax", "exponax", "matplotlib.pyplot", "phi", "phiml")
imported = [m for m in heavy if m in sys.modules]

from physgrad.harness import bench, plots
rows = [{"method": m, "seed": s, "split": "test", "metric": "loss", "wall_time": t, "value": v}
        for m in ("adam", "hig") for s in (0, 1) for t, v in ((0.0, 1.0), (1.0, 0.5 + s / 10))]
plots.loss_vs_time(rows, os.path.join(FIGURES, "loss.png"), order=["adam", "hig"])
cells = [({"clip": c}, [dict(r, epoch=int(r["wall_time"])) for r in rows]) for c in ("value", "norm")]
plots.grid_panels(cells, os.path.join(FIGURES, "grid.png"), panel="clip", methods=["adam", "hig"])
table = [{"method": m, "status": "ok", "ratio": r, "diverged": 0, "failed": 0} for m, r in (("adam", 1.0), ("hig", 0.1))]
bench.heatmap({"p": table}, os.path.join(FIGURES, "heat.png"))
figures = {"backend": matplotlib.get_backend(), "pyplot": "matplotlib.pyplot" in sys.modules}

modules = [m.name for m in pkgutil.walk_packages(physgrad.__path__, "physgrad.")
           if m.name != "physgrad.__main__"]  # __main__ runs the command line
for name in modules:
    importlib.import_module(name)
after = {k: repr(v) for k, v in jax.config.values.items()}
pools_after = {p["filepath"]: p["num_threads"] for p in threadpool_info()}
print(json.dumps({
    "imported": imported,
    "figures": figures,
    "modules": modules,
    "environ": sorted(k for k in set(environ) | set(os.environ) if environ.get(k) != os.environ.get(k)),
    "pools": [f for f in pools if pools_after.get(f) != pools[f]], "n_pools": len(pools),
    "changed": sorted(k for k in before if before[k] != after.get(k)),
    "x64": bool(jax.config.jax_enable_x64),
    "zeros": str(jnp.zeros(()).dtype),
    "arange": str(jnp.arange(3).dtype),
    "normal": str(jax.random.normal(jax.random.key(0), (2,)).dtype),
    "linear": str(eqx.nn.Linear(2, 2, key=jax.random.key(0)).weight.dtype),
}))
"""


@pytest.fixture(scope="module")
def fresh_imports(tmp_path_factory) -> tuple[dict, Path]:
    """What FRESH_IMPORTS saw, and the folder its figures are in."""
    tmp_path = tmp_path_factory.mktemp("imports")
    return run_fresh(f"FIGURES = {str(tmp_path)!r}\n{FRESH_IMPORTS}", tmp_path), tmp_path


@pytest.mark.costly("a fresh interpreter (x64 off, nothing imported); its module fixture serves the next two tests too")
def test_importing_every_physgrad_module_leaves_jax_configuration_alone(fresh_imports):
    info, _ = fresh_imports
    assert "physgrad.precision" in info["modules"] and "physgrad.problems.heat" in info["modules"]
    assert info["changed"] == []
    assert info["environ"] == [] and info["pools"] == [] and info["n_pools"] >= 1  # no variable, no thread pool
    assert info["x64"] is False
    assert (info["zeros"], info["arange"], info["normal"], info["linear"]) == ("float32", "int32", "float32", "float32")


def test_importing_physgrad_leaves_the_heavy_optional_packages_unimported(fresh_imports):
    """optimistix (the L-BFGS inverse), kfac-jax, exponax and pyplot are imported where they
    are used, not by ``import physgrad`` or its command line."""
    info, _ = fresh_imports
    assert info["imported"] == []


def test_figures_leave_the_matplotlib_backend_alone(fresh_imports):
    """The figures draw on their own Figure canvas: a notebook's backend (here: svg) stays,
    and pyplot is never imported."""
    info, figures = fresh_imports
    assert info["figures"] == {"backend": "svg", "pyplot": False}
    for name in ("loss.png", "grid.png", "heat.png"):
        assert (figures / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- (b) the update rules with x64 off ---------------------------------------------------
def gram_case(shape=(12, 40)):
    """A float32 J with singular values over three decades, the last one (1e-8) below
    τ = 1e-6 (dropped), and a g."""
    rng = np.random.default_rng(7)
    m, p = shape
    k = min(m, p)
    u, _ = np.linalg.qr(rng.standard_normal((m, k)))
    v, _ = np.linalg.qr(rng.standard_normal((p, k)))
    s = np.logspace(0, -3, k)
    s[-1] = 1e-8
    j = ((u * s) @ v.T).astype(np.float32)
    return j, rng.standard_normal(m).astype(np.float32)


def numpy_half_inverse(j, g, exponent=-0.5, truncation=1e-6):
    """V diag(s^κ) Uᵀ g over s > τ s_max, NumPy float64 SVD of the float32 inputs."""
    u, s, vt = np.linalg.svd(np.asarray(j, np.float64), full_matrices=False)
    keep = s > truncation * s.max()
    return vt[keep].T @ (s[keep] ** exponent * (u[:, keep].T @ np.asarray(g, np.float64)))


def small_oscillators():
    return problems.Oscillators(n_steps=16, n_train=16, n_test=8)


def hig_step(problem, batch_size=8):
    """One HIG step of ``problem`` from its initial network, written with the problem object
    and :func:`half_inverse` alone: per-sample Jacobians (vmap of jacrev), g = ∂L/∂y of the
    batch-mean loss, θ ← θ − η·J^{−1/2} g with the problem's HIG learning rate and τ."""
    from physgrad.harness.registry import paper_defaults

    hig = paper_defaults(type(problem), "hig")
    data = problem.make_data(jax.random.key(0))
    network = problem.make_network(jax.random.key(1))
    params, static = eqx.partition(network, eqx.is_inexact_array)
    flat, unravel = ravel_pytree(params)
    batch = jax.tree.map(lambda a: a[:batch_size], data["train"])

    @jax.jit
    def step(flat, batch):
        def predict(theta, sample):
            return problem.predict(eqx.combine(unravel(theta), static), sample).ravel()

        y = jax.vmap(predict, (None, 0))(flat, batch)
        jac = jax.vmap(jax.jacrev(predict), (None, 0))(flat, batch).reshape(-1, flat.size)
        g = jax.grad(lambda y: jnp.mean(jax.vmap(problem.loss)(y, batch)))(y).ravel()
        direction = half_inverse(jac, g, exponent=-0.5, truncation=hig["truncation"], route=Gram())
        return flat - hig["lr"] * direction, direction

    return step(flat, batch)


def lbfgs_case():
    """L-BFGS (float64 inside its own scope) on float32 inputs."""
    a = jnp.asarray([[2.0, 0.3], [0.1, 1.5]], jnp.float32)

    def simulate(x, sample):
        return a @ x + 0.1 * jnp.sin(x) + sample["shift"]

    x = jnp.asarray([0.3, -0.2], jnp.float32)
    sample = {"shift": jnp.float32(0.5)}
    y = simulate(x, sample)
    return LBFGS(max_steps=200, tol=1e-10)(simulate, x, y, y + jnp.asarray([0.1, -0.05], jnp.float32), sample)


def update_rule_arrays() -> dict[str, np.ndarray]:
    """Every x64-sensitive update piece on float32 inputs (computed on both sides)."""
    out = {}
    for name, shape in (("wide", (12, 40)), ("tall", (40, 12))):
        j, g = gram_case(shape)
        out[f"gram_{name}"] = half_inverse(jnp.asarray(j), jnp.asarray(g), exponent=-0.5, truncation=1e-6, route=Gram())
        out[f"gram_{name}_jit"] = jax.jit(lambda j, g: half_inverse(j, g, route=Gram()))(j, g)
    rng = np.random.default_rng(3)
    params = {"w": jnp.asarray(rng.standard_normal((3, 5)), jnp.float32)}
    batch = {"x": jnp.asarray(rng.standard_normal((8, 5)), jnp.float32)}
    g = jnp.asarray(rng.standard_normal(24), jnp.float32)
    predict = lambda p, s: jnp.tanh(p["w"] @ s["x"])  # noqa: E731
    out["blockgram"] = jax.jit(lambda p, b, g: blockgram_half_inverse(predict, p, b, g, blocks=4))(params, batch, g)
    out["lanczos"], out["lanczos_change"] = lanczos_half_inverse(predict, params, batch, g, steps=6)
    result = lbfgs_case()
    out["lbfgs_x"], out["lbfgs_converged"] = result.x, result.converged
    out["hig_params"], out["hig_direction"] = hig_step(small_oscillators())
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def fresh_update_rules(tmp_path_factory):
    return save_in_fresh("update_rule_arrays", tmp_path_factory.mktemp("rules"))


@pytest.mark.costly("x64 off needs a fresh interpreter; its module fixture serves the next three tests too")
def test_update_rules_with_x64_off_are_float32_and_equal_the_x64_results(fresh_update_rules):
    here = update_rule_arrays()  # x64 on (conftest)
    assert set(fresh_update_rules) == set(here)
    for name, want in here.items():
        got = fresh_update_rules[name]
        if name == "lanczos_change":  # the caller's default float: float32 where x64 is off
            assert got.dtype == np.float32 and want.dtype == np.float64
            np.testing.assert_allclose(got, want, rtol=1e-6)
            continue
        assert got.dtype == want.dtype and got.dtype in (np.float32, np.bool_), name
        np.testing.assert_array_equal(got, want, err_msg=name)


@pytest.mark.parametrize("shape", ["wide", "tall"])
def test_gram_route_with_x64_off_equals_numpy_float64_to_float32_rounding(fresh_update_rules, shape):
    j, g = gram_case((12, 40) if shape == "wide" else (40, 12))
    want = numpy_half_inverse(j, g)
    got = fresh_update_rules[f"gram_{shape}"]
    # Formed and decomposed in float64, rounded once to float32 at the end.
    np.testing.assert_allclose(got, want, rtol=2e-7, atol=2e-7 * np.abs(want).max())


def test_hig_step_with_x64_off_takes_a_finite_step(fresh_update_rules):
    direction = fresh_update_rules["hig_direction"]
    assert np.all(np.isfinite(direction)) and np.linalg.norm(direction) > 0
    assert fresh_update_rules["hig_params"].dtype == np.float32


# --- (c) float32 problems: float32 data and networks, identical either way ---------------
def float32_problem_arrays() -> dict[str, np.ndarray]:
    """make_data and make_network of four float32 problems (small settings), flattened. For
    KS the training split's reference trajectories and the coarse solvers (built in float64,
    rounded to float32) stand for make_data: the other splits only repeat the generator."""
    chosen = {
        "oscillators": problems.Oscillators(n_train=32, n_test=32),
        "poisson_hig": problems.PoissonHig(n_train=32, n_test=32),
        "cartpole": problems.CartPole(n_train=16, n_test=16),
    }
    trees = {}
    for name, problem in chosen.items():
        trees[f"{name}/data"] = problem.make_data(jax.random.key(0))
        trees[f"{name}/net"] = problem.make_network(jax.random.key(1))
    ks = problems.KuramotoSivashinsky(n_ics=1, warmup_frames=10, frames=30, dataset_fraction=1.0, width=8, blocks=2)
    trees["ks/data"] = ks.generate("train")
    trees["ks/solvers"] = ks.solvers()[0]
    trees["ks/net"] = ks.make_network(jax.random.key(1))
    out = {}
    for prefix, tree in trees.items():
        for path, leaf in jax.tree_util.tree_leaves_with_path(eqx.filter(tree, eqx.is_array)):
            out[f"{prefix}{jax.tree_util.keystr(path)}"] = np.asarray(leaf)
    return out


@pytest.mark.slow  # builds four problems twice (a fresh interpreter and this one): a minute
def test_float32_problems_build_identical_float32_arrays_with_x64_off(tmp_path, monkeypatch):
    fresh = save_in_fresh("float32_problem_arrays", tmp_path)
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "cache_x64"))  # regenerate here too
    here = float32_problem_arrays()  # x64 on
    assert set(fresh) == set(here)
    for name, got in fresh.items():
        assert got.dtype in (np.float32, np.int32, np.complex64, np.bool_), (name, got.dtype)
        assert got.dtype == here[name].dtype, name
        np.testing.assert_array_equal(got, here[name], err_msg=name)


# --- float64 problems ----------------------------------------------------------------------
def test_needs_float64_marks_the_float64_problems():
    assert problems.Heat().needs_float64 and problems.Toy2d().needs_float64
    assert problems.Oscillators(dtype="float64").needs_float64 and problems.PoissonHig(dtype="float64").needs_float64
    for problem in (problems.Oscillators(), problems.QuantumDipole(), problems.CartPole(), problems.Poisson(),
                    problems.KuramotoSivashinsky(), problems.Sine()):  # fmt: skip
        assert not problem.needs_float64, problem.name


def test_a_float64_problem_without_x64_fails_in_one_line():
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match=r"heat computes in float64: run it inside `with jax.enable_x64\(True\):`"):
            problems.Heat(n_train=2, n_test=2, resolution=8).make_data(jax.random.key(0))
        with pytest.raises(ValueError, match="oscillators with dtype=float64 computes in float64"):
            problems.Oscillators(dtype="float64").make_network(jax.random.key(0))
        with pytest.raises(ValueError, match="toy2d computes in float64"):
            problems.Toy2d().make_data(jax.random.key(0))


# A fresh interpreter builds Heat's data (10 s of CPU); the fast tier checks the scope itself
# with x64 off in this process (test_precision_helpers) and the one-line refusal above.
@pytest.mark.slow
def test_a_float64_problem_runs_inside_a_scope_and_leaves_x64_off(tmp_path):
    info = run_fresh(
        """
        import json, jax, jax.numpy as jnp
        from physgrad.problems import Heat
        problem = Heat(n_train=2, n_test=2, resolution=8, levels=1, filters=2)
        with jax.enable_x64(True):
            data = problem.make_data(jax.random.key(0))
            network = problem.make_network(jax.random.key(1))
            sample = jax.tree.map(lambda a: a[0], data["test"])
            loss = problem.loss(problem.predict(network, sample), sample)
        print(json.dumps({"y": str(data["train"]["y"].dtype), "loss": str(loss.dtype),
                          "x64": bool(jax.config.jax_enable_x64), "zeros": str(jnp.zeros(()).dtype)}))
        """,
        tmp_path,
    )
    assert info == {"y": "float64", "loss": "float64", "x64": False, "zeros": "float32"}


# --- the precision helpers -----------------------------------------------------------------
def test_precision_helpers():
    x = {"a": jnp.ones(2, jnp.float32), "c": jnp.ones(2, jnp.complex64), "i": jnp.arange(2, dtype=jnp.int32)}
    with jax.enable_x64(False):
        with pytest.raises(RuntimeError, match="inside physgrad.precision.float64_scope"):
            to_float64(x)
        with float64_scope(False):
            assert not jax.config.jax_enable_x64
        with float64_scope():
            wide = to_float64(x)
            assert (wide["a"].dtype, wide["c"].dtype, wide["i"].dtype) == (jnp.float64, jnp.complex128, jnp.int32)
            back = cast_like(wide, x)
        assert not jax.config.jax_enable_x64
    assert jax.tree.map(lambda a: a.dtype, back) == jax.tree.map(lambda a: a.dtype, x)

"""Reverse-mode-only simulators (a ``jax.custom_vjp``, e.g. PhiFlow's solves) in the
Jacobian- and Hessian-based pieces, with plain JAX stand-ins (no PhiFlow needed).

- ``GaussNewton(jacobian=AutoMode())`` detects at trace time that the simulator has no forward
  mode (a mark, or a JVP probe under ``jax.eval_shape``), builds J by ``jacrev`` and equals
  NumPy's pinv step of the same map written without custom_vjp;
- the forward-mode pieces (``LinearSolve``; ``GaussNewton(jacobian=ForwardMode())``) raise one
  line naming the alternative; the Hessian pieces (``SaddleFreeNewton``, ``newton``) fall
  back to reverse over reverse where forward over reverse fails, and raise one line when
  both fail.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad import jacobian
from physgrad.inverse import GaussNewton, LinearSolve, SaddleFreeNewton

RNG = np.random.default_rng(3)
A = RNG.normal(size=(4, 4))


def plain(x):
    """A smooth nonlinear map R⁴ → R⁴ (ordinary JAX: forward and reverse mode)."""
    return jnp.asarray(A) @ x + 0.1 * jnp.sin(x)


def np_plain(x):
    return A @ x + 0.1 * np.sin(x)


def np_jacobian(x):
    return A + np.diag(0.1 * np.cos(x))


@jax.custom_vjp
def reverse_only(x):
    """``plain`` behind a custom_vjp: ``jax.jvp`` raises, ``jax.vjp`` works."""
    return plain(x)


reverse_only.defvjp(lambda x: (plain(x), x), lambda x, g: (jax.vjp(plain, x)[1](g)[0],))


def _vjp_plain(x, g):
    return jax.vjp(plain, x)[1](g)[0]


@jax.custom_vjp
def _adjoint(x, g):
    """``J(x)ᵀ g`` behind its own custom_vjp (PhiML's adjoint solve is one)."""
    return _vjp_plain(x, g)


_adjoint.defvjp(lambda x, g: (_vjp_plain(x, g), (x, g)), lambda res, ct: jax.vjp(_vjp_plain, *res)[1](ct))


@jax.custom_vjp
def nested(x):
    """As PhiML's solves: the backward pass applies another custom_vjp, so forward over
    reverse (jax.hessian) fails too; reverse over reverse works."""
    return plain(x)


nested.defvjp(lambda x: (plain(x), x), lambda x, g: (_adjoint(x, g),))


@jax.custom_vjp
def opaque(x):
    """A backward pass through a host callback: no second derivative in any mode."""
    return plain(x)


def _opaque_bwd(x, g):
    vjp = lambda x, g: np.asarray(np_jacobian(np.asarray(x)).T @ np.asarray(g), np.asarray(g).dtype)  # noqa: E731
    return (jax.pure_callback(vjp, jax.ShapeDtypeStruct(g.shape, g.dtype), x, g, vmap_method="sequential"),)


opaque.defvjp(lambda x: (plain(x), x), _opaque_bwd)

X = RNG.normal(size=4)
Y_TARGET = np_plain(X) + 0.1 * RNG.normal(size=4)


def simulate(fn):
    return lambda x, sample: fn(x) + sample["shift"]


SAMPLE = {"shift": jnp.float64(0.0)}


def solve(solver, fn):
    return solver(simulate(fn), jnp.asarray(X), fn(jnp.asarray(X)), jnp.asarray(Y_TARGET), SAMPLE)


def solve_compiled(solver, fn):
    """``solve`` as one program, as SIP runs a solver (eagerly, each operation of the solve and
    of its derivatives compiles on its own: 2-3x the CPU); the mode is still chosen at trace time."""
    return eqx.filter_jit(lambda x, y, target: solver(simulate(fn), x, y, target, SAMPLE))(
        jnp.asarray(X), fn(jnp.asarray(X)), jnp.asarray(Y_TARGET)
    )


def test_the_probe_tells_reverse_only_functions_apart_at_trace_time():
    x = jnp.asarray(X)
    assert jacobian.supports_forward_mode(plain, x)
    assert not jacobian.supports_forward_mode(reverse_only, x)
    assert not jacobian.supports_forward_mode(lambda z: 2.0 * reverse_only(z), x)  # through a closure
    # inside jit and vmap (tracers) too
    modes = []
    jax.jit(jax.vmap(lambda z: modes.append(jacobian.jacobian_mode(reverse_only, z, 4)) or z))(jnp.stack([x, x]))
    assert modes == ["reverse"]
    assert jacobian.jacobian_mode(plain, x, 4) == "forward"
    assert jacobian.jacobian_mode(plain, x, 3) == "reverse"  # fewer outputs than inputs
    marked = jacobian.mark_reverse_only(lambda z: plain(z))
    assert jacobian.is_reverse_only(marked) and jacobian.is_reverse_only(eqx.Partial(marked))
    assert not jacobian.supports_forward_mode(marked, x)  # the mark alone decides
    # a sample with an integer leaf (a time-stepper's solver index) gets a float0 tangent there
    indexed = lambda z, sample: plain(z) * sample["index"].astype(z.dtype)  # noqa: E731
    assert jacobian.supports_forward_mode(indexed, x, {"index": jnp.asarray(2, jnp.int32)})
    with pytest.raises(ValueError, match="unknown jacobian mode"):
        jacobian.jacobian_mode(plain, x, 4, "sideways")


@pytest.mark.parametrize("mode", [jacobian.AutoMode(), jacobian.ReverseMode()])
def test_gauss_newton_on_a_reverse_only_simulator_equals_numpy_pinv(mode):
    result = solve_compiled(GaussNewton(1e-10, jacobian=mode), reverse_only)
    expected = X + np.linalg.pinv(np_jacobian(X), rcond=1e-10) @ (Y_TARGET - np_plain(X))
    np.testing.assert_allclose(result.x, expected, rtol=1e-10, atol=1e-12)
    # and the forward-mode answer on the ordinary function is the same step
    forward = solve_compiled(GaussNewton(1e-10, jacobian=jacobian.ForwardMode()), plain)
    np.testing.assert_allclose(result.x, forward.x, rtol=1e-12, atol=1e-13)
    assert bool(result.converged)


def test_gauss_newton_under_sip_style_jit_and_vmap_picks_reverse_mode():
    solver = GaussNewton(1e-10)
    xs = jnp.stack([jnp.asarray(X), jnp.asarray(X) + 0.1])
    run = jax.jit(
        jax.vmap(lambda x: solver(simulate(reverse_only), x, reverse_only(x), jnp.asarray(Y_TARGET), SAMPLE).x)
    )
    for x, got in zip(np.asarray(xs), np.asarray(run(xs))):
        want = x + np.linalg.pinv(np_jacobian(x), rcond=1e-10) @ (Y_TARGET - np_plain(x))
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def test_jacobian_mode_names_are_deprecated_spellings_of_the_mode_objects():
    with pytest.warns(DeprecationWarning, match="ReverseMode") as warned:
        assert GaussNewton(jacobian="reverse") == GaussNewton(jacobian=jacobian.ReverseMode())
    assert warned[0].filename == __file__  # the user's line, not physgrad's or Equinox's
    assert GaussNewton().jacobian == jacobian.AutoMode()


def test_forward_mode_pieces_say_so_in_one_line():
    with pytest.raises(
        ValueError, match=r"^GaussNewton\(jacobian='forward'\) needs forward-mode .*jacobian='reverse'"
    ) as info:
        solve(GaussNewton(jacobian=jacobian.ForwardMode()), reverse_only)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"^LinearSolve needs forward-mode .*GaussNewton\(\).*LBFGS\(\)") as info:
        solve(LinearSolve(), reverse_only)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="unknown jacobian"):
        GaussNewton(jacobian="both")


@pytest.mark.parametrize("fn", [reverse_only, nested], ids=["custom_vjp", "nested_custom_vjp"])
def test_saddle_free_newton_falls_back_to_reverse_over_reverse(fn):
    # jax.hessian (forward over reverse) differentiates a plain backward pass, not a nested one
    forward_over_reverse = jacobian.supports_forward_mode(
        lambda z: jnp.sum(fn(z)), jnp.asarray(X), transform=jax.hessian
    )
    assert forward_over_reverse == (fn is reverse_only)
    got = solve_compiled(SaddleFreeNewton(0.2), fn)
    want = solve_compiled(SaddleFreeNewton(0.2), plain)
    np.testing.assert_allclose(got.x, want.x, rtol=1e-10, atol=1e-12)


def test_hessian_pieces_name_the_alternative_when_no_second_derivative_exists():
    with pytest.raises(ValueError, match=r"^SaddleFreeNewton needs a Hessian.*GaussNewton\(\)") as info:
        solve(SaddleFreeNewton(0.2), opaque)
    assert "\n" not in str(info.value)

    def predict(params, sample):
        return opaque(params["w"] * sample["x"])

    estimate = physgrad.newton(predict, lambda y, sample: jnp.sum(y**2))
    batch = {"x": jnp.ones((2, 4))}
    with pytest.raises(ValueError, match=r"^newton needs a Hessian.*gauss_newton or hig") as info:
        estimate({"w": jnp.asarray(X)}, batch)
    assert "\n" not in str(info.value)


def test_newton_on_a_nested_custom_vjp_equals_newton_on_the_plain_map():
    def make(fn):
        return physgrad.newton(lambda p, s: fn(p["w"] * s["x"]), lambda y, s: jnp.sum((y - 1.0) ** 2))

    batch = {"x": jnp.asarray(1.0 + 0.1 * RNG.normal(size=(2, 4)))}
    params = {"w": jnp.asarray(X)}
    got, _ = jax.jit(make(nested))(params, batch)  # each compiled as one program, as a step runs it
    want, _ = jax.jit(make(plain))(params, batch)
    np.testing.assert_allclose(got["w"], want["w"], rtol=1e-9, atol=1e-12)


def test_lbfgs_works_on_a_reverse_only_simulator():
    """optimistix's L-BFGS gets its gradient by linearize + transpose: reverse mode."""
    from physgrad.inverse import LBFGS

    got, want = solve_compiled(LBFGS(), reverse_only), solve_compiled(LBFGS(), plain)
    np.testing.assert_allclose(got.x, want.x, rtol=1e-10, atol=1e-12)
    assert bool(got.converged)

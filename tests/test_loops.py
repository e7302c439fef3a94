"""physgrad.loops.scan: unrolled exactly where a convolution would run in a CPU loop body,
with lax.scan's results (the reference: lax.scan itself, and a Python loop)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from physgrad import loops

W = jax.random.normal(jax.random.key(0), (2, 2, 3)) * 0.3


def conv_body(c, x):
    c = jnp.tanh(jax.lax.conv_general_dilated(c, W, (1,), "SAME")) + x
    return c, jnp.sum(c)


def dense_body(c, x):
    c = jnp.tanh(c @ jnp.ones((8, 8)) * 0.1) + x
    return c, jnp.sum(c)


def test_unrolls_a_short_convolutional_scan_on_a_cpu_only():
    c, xs = jnp.ones((1, 2, 8)), jnp.zeros((4, 1, 2, 8))
    assert loops.unrolls(conv_body, c, xs, backend="cpu")
    assert loops.unrolls(jax.checkpoint(conv_body), c, xs, backend="cpu")  # nested in a remat
    assert not loops.unrolls(conv_body, c, xs, backend="gpu")
    assert not loops.unrolls(dense_body, jnp.ones((8,)), jnp.zeros((4, 8)), backend="cpu")
    long = jnp.zeros((loops.MAX_UNROLL + 1, 1, 2, 8))
    assert not loops.unrolls(conv_body, c, long, backend="cpu")
    assert loops.unrolls(lambda c, _: conv_body(c, 0.0), c, None, length=loops.MAX_UNROLL, backend="cpu")


def test_scan_gives_lax_scans_results_and_gradients_without_a_loop_for_a_convolution():
    c = jax.random.normal(jax.random.key(1), (1, 2, 8))
    xs = jax.random.normal(jax.random.key(2), (5, 1, 2, 8)) * 0.1
    for reverse in (False, True):
        ours = jax.jit(lambda c, xs, r=reverse: loops.scan(conv_body, c, xs, reverse=r))
        ref = jax.lax.scan(conv_body, c, xs, reverse=reverse)
        for a, b in zip(jax.tree.leaves(ours(c, xs)), jax.tree.leaves(ref)):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
        if jax.default_backend() == "cpu":
            assert "while" not in ours.lower(c, xs).as_text()
    # a Python loop, and the gradient through the unrolled scan
    carry, ys = c, []
    for x in xs:
        carry, y = conv_body(carry, x)
        ys.append(y)
    got = loops.scan(conv_body, c, xs)
    np.testing.assert_allclose(got[0], carry, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got[1], jnp.stack(ys), rtol=1e-5)
    grad = jax.grad(lambda c: jnp.sum(loops.scan(conv_body, c, xs)[1]))(c)
    ref_grad = jax.grad(lambda c: jnp.sum(jax.lax.scan(conv_body, c, xs)[1]))(c)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-5, atol=1e-6)
    # a dense body keeps its loop
    dense = jax.jit(lambda c, xs: loops.scan(dense_body, c, xs))
    assert "while" in dense.lower(jnp.ones((8,)), jnp.zeros((5, 8))).as_text()


def test_scan_runs_as_lax_scan_under_disable_jit_and_says_what_lax_scan_says():
    """Under disable_jit the body runs eagerly (Python control flow on values is allowed), so
    no abstract trace of it is made; a scan with neither xs nor length fails in lax.scan's words."""

    def body(c, _):
        if float(jnp.sum(c)) > 1e9:  # concrete values only
            return c, c
        return conv_body(c, 0.0)

    c = jnp.ones((1, 2, 8))
    with jax.disable_jit():
        got = loops.scan(body, c, None, length=3)
        ref = jax.lax.scan(body, c, None, length=3)
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-6)
    for scan in (loops.scan, jax.lax.scan):
        try:
            scan(conv_body, c)
        except ValueError as error:
            message = str(error)
        else:
            raise AssertionError("no error")
        assert "length" in message, message

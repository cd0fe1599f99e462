"""The differentiable Householder QR and the frame of ker A it gives."""

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax._householder
from nhjax._householder import (
    householder_frame,
    householder_frame_operator,
    householder_pivots,
    householder_signs,
    householder_stable_frame,
)


def _matrix(seed, n, k):
    return jax.random.normal(jax.random.key(seed), (n, k), dtype=jnp.float64)


@jax.jit
def _frame_and_pivot(a_t):
    signs = householder_signs(a_t)
    frame, pivot = householder_frame(a_t, signs)
    return frame, pivot, signs


@hypothesis.settings(deadline=None, max_examples=40)
@hypothesis.given(seed=st.integers(0, 2**31 - 1), shape=st.sampled_from([(3, 1), (4, 2), (7, 1), (6, 3), (5, 4), (9, 6)]))
def test_frame_is_the_complement_of_lapacks_householder_qr(seed, shape):
    """The stable signs are LAPACK's (its reflector of x is x + sign(x_1)|x| e_1, so
    R_jj = -s_j |R_jj|), so the frame is the last n - k columns of LAPACK's complete Q,
    an independent implementation of the same factorisation. (9, 6): more reflections
    than are unrolled, so by `lax.scan`."""
    n, k = shape
    a_t = _matrix(seed, n, k)
    frame, pivot, signs = _frame_and_pivot(a_t)
    q, r = np.linalg.qr(np.asarray(a_t), mode="complete")
    np.testing.assert_allclose(frame, q[:, k:], atol=1e-14)
    np.testing.assert_allclose(a_t.T @ frame, 0.0, atol=1e-14)  # A X = 0
    np.testing.assert_allclose(frame.T @ frame, np.eye(n - k), atol=1e-14)
    np.testing.assert_allclose(np.diag(r[:k]), -signs * np.abs(np.diag(r[:k])), atol=0)
    assert float(pivot) >= float(np.min(np.abs(np.diag(r[:k])))) * (1 - 1e-14)


def _constraint_matrix(q):
    """A smooth (2, 4) constraint matrix, full rank near the test points."""
    return jnp.stack(
        [
            jnp.array([1.0, 0.0, 0.0, 0.0]) + jnp.stack([0.0 * q[0], jnp.sin(q[2]), q[0] * q[1], 0.0 * q[0]]),
            jnp.stack([jnp.cos(q[3]), 1.0 + 0.0 * q[0], 0.0 * q[0], q[1] ** 2]),
        ]
    )


def test_frame_derivative_by_autodiff_matches_central_differences():
    q = jnp.array([0.3, -0.7, 1.1, 0.4])
    signs = householder_signs(_constraint_matrix(q).T)
    frame = jax.jit(lambda x: householder_frame(_constraint_matrix(x).T, signs)[0])
    forward = jax.jit(jax.jacfwd(frame))(q)
    reverse = jax.jit(jax.jacrev(frame))(q)
    step = 1e-5
    central = jnp.stack(
        [(frame(q + step * e) - frame(q - step * e)) / (2 * step) for e in jnp.eye(4)], axis=-1
    )
    np.testing.assert_allclose(forward, central, atol=1e-9)
    np.testing.assert_allclose(forward, reverse, atol=1e-14)


@pytest.mark.parametrize("shape", [(5, 2), (9, 6)])
def test_the_stable_frame_is_the_frame_with_the_signs_it_returns(shape):
    """One factorisation for a step's signs and its frame at the start: the frame with
    the stable signs, and its derivative, are those of the factorisation given the
    signs it returns (to rounding: the two programs may fuse differently), and the
    signs are `householder_signs`'. (9, 6): more reflections than are unrolled
    (LAPACK's, differentiated in closed form)."""
    n, k = shape
    a_t, direction = _matrix(3, n, k), _matrix(4, n, k)
    v = jnp.linspace(-1.0, 1.0, n)

    def stable(a):
        frame, signs = householder_stable_frame(a)
        return frame.vectors, frame.transpose_times(v), signs

    (vectors, products, signs), (vectors_dot, products_dot, _) = jax.jit(
        lambda a, d: jax.jvp(stable, (a,), (d,))
    )(a_t, direction)

    def given(a):
        frame = householder_frame_operator(a, signs)
        return frame.vectors, frame.transpose_times(v)

    (given_vectors, given_products), (given_vectors_dot, given_products_dot) = jax.jit(
        lambda a, d: jax.jvp(given, (a,), (d,))
    )(a_t, direction)
    np.testing.assert_array_equal(signs, householder_signs(a_t))
    for ours, theirs in [
        (vectors, given_vectors),
        (products, given_products),
        (vectors_dot, given_vectors_dot),
        (products_dot, given_products_dot),
    ]:
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-14)
        assert np.max(np.abs(ours)) > 0.1


def test_frame_products_and_their_derivative_match_the_formed_frame():
    """X^T v and X w from the reflectors applied to v and w, and the derivative of
    X^T v in q at fixed v, against the formed frame and the contraction of its whole
    derivative with v."""
    q = jnp.array([0.3, -0.7, 1.1, 0.4])
    v = jnp.array([0.9, -0.2, 0.5, 1.3])
    signs = householder_signs(_constraint_matrix(q).T)
    frame = lambda x: householder_frame(_constraint_matrix(x).T, signs)[0]  # noqa: E731
    transpose_times = lambda x: householder_frame_operator(_constraint_matrix(x).T, signs).transpose_times(v)  # noqa: E731
    np.testing.assert_allclose(jax.jit(transpose_times)(q), frame(q).T @ v, atol=1e-15)
    w = jnp.array([0.7, -1.1])
    np.testing.assert_allclose(householder_frame_operator(_constraint_matrix(q).T, signs).times(w), frame(q) @ w, atol=1e-15)
    contracted = jnp.einsum("j,jai->ai", v, jax.jit(jax.jacfwd(frame))(q))
    np.testing.assert_allclose(jax.jit(jax.jacfwd(transpose_times))(q), contracted, atol=1e-14)


def test_fixed_signs_give_one_smooth_frame_nearby():
    """With s fixed, X(q + t d; s) varies by O(t); with the signs recomputed at a point
    where a pivot's sign flips, the frame jumps."""
    # The first column's leading entry is sin(theta): its stable sign flips at theta = 0.
    constraints = lambda theta: jnp.stack([jnp.sin(theta), jnp.cos(theta), 0.0 * theta])[:, None]  # noqa: E731
    signs = householder_signs(constraints(jnp.array(1e-3)))
    frame = lambda theta, s: householder_frame(constraints(theta), s)[0]  # noqa: E731
    for t in [1e-2, 1e-4, 1e-6]:
        change = jnp.max(jnp.abs(frame(jnp.array(1e-3 - t), signs) - frame(jnp.array(1e-3), signs)))
        assert float(change) <= 2 * t
    other_side = jnp.array(-1e-3)
    jump = frame(other_side, householder_signs(constraints(other_side))) - frame(jnp.array(1e-3), signs)
    assert float(jnp.max(jnp.abs(jump))) > 0.5


@pytest.mark.parametrize("dtype, tolerance", [(jnp.float32, 1e-6), (jnp.float64, 1e-15)])
def test_rank_loss_shows_in_the_pivot(dtype, tolerance):
    full = jnp.array([[1.0, 0.0, 2.0], [0.0, 1.0, 1.0]], dtype=dtype).T
    parallel = jnp.array([[1.0, 0.0, 2.0], [2.0, 0.0, 4.0]], dtype=dtype).T
    _, pivot_full = householder_frame(full, householder_signs(full))
    _, pivot_parallel = householder_frame(parallel, householder_signs(parallel))
    assert float(pivot_full) > 0.5
    assert float(pivot_parallel) <= 10 * tolerance


def _wide_constraints(q):
    """A smooth (6, 10) constraint matrix: more rows than the reflections that are
    unrolled (`UNROLLED_REFLECTIONS`)."""
    rows = jnp.arange(6)
    a = jnp.zeros((6, 10)).at[rows, rows].set(1.0 + 0.1 * jnp.cos(q[rows]))
    return a.at[rows, rows + 4].set(jnp.sin(q[rows + 2]) * q[rows + 1]).at[rows, 9].add(0.3 * q[0])


def _with_unrolled_reflections(function):
    """`function()` with every loop over reflections unrolled. The factorisation and the
    products are jitted, so JAX's caches are cleared on the way in and out: their traces
    for the same shapes would be reused otherwise (clearing the two functions' own
    caches is not enough: their traces are cached by JAX's tracing too)."""
    jax.clear_caches()
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(nhjax._householder, "UNROLLED_REFLECTIONS", 16)
            return function()
    finally:
        jax.clear_caches()


@pytest.mark.parametrize("flipped", [None, 2], ids=["stable signs", "one sign flipped"])
def test_scanned_and_unrolled_reflections_agree(flipped):
    """Above `UNROLLED_REFLECTIONS` constraints the factorisation is LAPACK's QR, or
    where a given sign is not the stable one (`flipped`: the third) a scan over the
    reflections, differentiated in closed form, and the products with the frame in
    the compact WY form: the same values, products and derivatives (first and second,
    of the pivots too) as the unrolled reflections differentiated step by step, to
    roundoff."""
    assert nhjax._householder.UNROLLED_REFLECTIONS < 6
    q = jnp.linspace(-0.8, 1.1, 10)
    v = jnp.linspace(0.5, -1.5, 10)
    w = jnp.linspace(-0.3, 0.9, 4)
    signs = householder_signs(_wide_constraints(q).T)
    if flipped is not None:
        signs = signs.at[flipped].multiply(-1)

    def product(x):
        return householder_frame_operator(_wide_constraints(x).T, signs).transpose_times(v)

    def everything(x):
        a_t = _wide_constraints(x).T
        operator = householder_frame_operator(a_t, signs)
        return dict(
            frame=householder_frame(a_t, signs)[0],
            pivots=householder_pivots(a_t, signs),
            stable_signs=householder_signs(a_t),
            transpose_times=operator.transpose_times(v),
            times=operator.times(w),
            times_matrix=operator.times(jnp.outer(w, v[:3])),
            derivative=jax.jacfwd(product)(x),
            reverse_derivative=jax.jacrev(product)(x),
            second_derivative=jax.hessian(lambda y: product(y) @ w)(x),
            times_derivative=jax.jacrev(lambda y: householder_frame_operator(_wide_constraints(y).T, signs).times(w))(x),
            pivot_derivatives=jax.jacfwd(lambda y: householder_pivots(_wide_constraints(y).T, signs))(x),
        )

    scanned = jax.jit(everything)(q)
    unrolled = _with_unrolled_reflections(lambda: jax.jit(everything)(q))
    for name in scanned:
        for a, b in zip(jax.tree.leaves(scanned[name]), jax.tree.leaves(unrolled[name])):
            np.testing.assert_allclose(a, b, atol=1e-14, err_msg=name)
    frame = scanned["frame"]
    np.testing.assert_allclose(_wide_constraints(q) @ frame, 0.0, atol=1e-14)
    np.testing.assert_allclose(frame.T @ frame, np.eye(4), atol=1e-14)
    np.testing.assert_allclose(scanned["transpose_times"], frame.T @ v, atol=1e-14)


def test_gonzalez_r_with_many_constraints_keeps_its_invariants_and_the_unrolled_run():
    """GONZALEZ-R with six constraints (the scanned factorisation with its closed-form
    derivative, products in the compact WY form): energy and constraint to roundoff,
    and the run with the reflections unrolled and differentiated step by step, to
    roundoff over 40 steps."""
    system = nhjax.NonholonomicSystem(
        lambda q, p, args: 0.5 * p @ p + jnp.sum(1 - jnp.cos(q[1:] - q[:-1])) + 0.5 * q @ q,
        lambda q, args: _wide_constraints(q),
    )
    q0 = jnp.linspace(-0.4, 0.5, 10)
    y0 = (q0, system.project_momentum(q0, jnp.cos(jnp.arange(10.0))))

    def run():
        return jax.jit(lambda y: nhjax.integrate(system, nhjax.GonzalezR(), y, 0.1, 40))(y0)

    scanned = run()
    unrolled = _with_unrolled_reflections(run)
    assert bool(jnp.all(jnp.isfinite(scanned.energy)))
    np.testing.assert_allclose(scanned.energy, scanned.energy[0], rtol=0, atol=1e-14 * float(jnp.abs(scanned.energy[0])))
    assert float(jnp.max(jnp.abs(scanned.constraint))) < 1e-14
    for a, b in zip(jax.tree.leaves(scanned.ys), jax.tree.leaves(unrolled.ys)):
        np.testing.assert_allclose(a, b, atol=1e-12)
    # The motion is not trivial: the run would not show a wrong frame otherwise.
    assert float(jnp.max(jnp.abs(scanned.ys[0][-1] - q0))) > 0.1

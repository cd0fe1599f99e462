"""The unrolled small dense linear algebra against LAPACK, on random matrices."""

import re

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from nhjax._linalg import (
    blocked_product,
    inverse,
    is_accurate_inverse,
    is_diagonally_dominant,
    jacobian_by_differences,
    lapack_inverse,
    LAPACK_SPLIT_WORK,
    product,
    PRODUCT_LIMIT,
    row_blocks,
    ROW_BLOCK_LIMIT,
    safe_norm,
    SEQUENTIAL_BYTES,
    solve,
    solve_spd,
    SPD_UNROLL_LIMIT,
    triangular_solve,
    UNROLL_LIMIT,
)


settings.register_profile("nhjax", max_examples=25, deadline=None, derandomize=True)
settings.load_profile("nhjax")
# Compiled once per size, as nhjax uses them, rather than dispatched op by op.
jitted_inverse, jitted_solve_spd = jax.jit(inverse), jax.jit(solve_spd)


@given(n=st.integers(1, 9), seed=st.integers(0, 2**31 - 1))
def test_inverse_with_pivoting_matches_lapack(n, seed):
    a = jax.random.normal(jax.random.key(seed), (n, n))
    np.testing.assert_allclose(jitted_inverse(a), jnp.linalg.inv(a), rtol=1e-9, atol=1e-9 * float(jnp.abs(jnp.linalg.inv(a)).max()))


@given(n=st.integers(1, 13), seed=st.integers(0, 2**31 - 1), by_rows=st.booleans())
def test_inverse_without_pivoting_matches_lapack_on_dominant_matrices(n, seed, by_rows):
    """Diagonally dominant by rows or by columns, with off-diagonal entries as large as
    the diagonal allows (no pivoting needed: Higham Thm 9.9)."""
    off = jax.random.uniform(jax.random.key(seed), (n, n), minval=-1.0, maxval=1.0) * (1 - jnp.eye(n))
    sums = jnp.sum(jnp.abs(off), axis=1 if by_rows else 0)
    a = off + jnp.diag(jnp.where(jnp.arange(n) % 2 == 0, 1.01, -1.01) * (sums + 1e-3))
    assert bool(is_diagonally_dominant(a))
    np.testing.assert_allclose(
        jax.jit(lambda a: inverse(a, pivoting=False))(a), jnp.linalg.inv(a), rtol=1e-10, atol=1e-10 * float(jnp.abs(jnp.linalg.inv(a)).max())
    )


@pytest.mark.parametrize("m, k, n", [(3, 2, 4), (7, 6, 7), (1, 5, 1), (PRODUCT_LIMIT + 1, 3, 2)])
def test_product_is_the_matrix_product(m, k, n):
    a = jax.random.normal(jax.random.key(m), (m, k))
    b = jax.random.normal(jax.random.key(n), (k, n))
    for left, right in ((a, b[:, 0]), (a[0], b), (a[0], b[:, 0])):
        np.testing.assert_allclose(jax.jit(product)(left, right), left @ right, rtol=1e-14, atol=1e-14)
    with pytest.raises(ValueError, match="two matrices"):
        product(a, b)


def test_diagonal_dominance():
    assert bool(is_diagonally_dominant(jnp.array([[2.0, 1.5], [0.1, 1.0]])))  # by columns, not by rows
    assert bool(is_diagonally_dominant(jnp.array([[2.0, 0.1], [1.5, 1.0]])))  # by rows, not by columns
    assert not bool(is_diagonally_dominant(jnp.array([[1.0, 1.0], [1.0, 3.0]])))  # ties are not strict
    assert not bool(is_diagonally_dominant(jnp.array([[1.0, 2.0, 0.0], [0.0, 1.0, 0.0], [2.0, 0.0, 1.0]])))


def test_is_accurate_inverse():
    a = jnp.array([[2.0, 1.0], [1.0, 3.0]])
    exact = jnp.linalg.inv(a)
    assert bool(is_accurate_inverse(a, exact))
    assert not bool(is_accurate_inverse(a, exact + 1e-6))
    assert not bool(is_accurate_inverse(a, exact.at[0, 0].set(jnp.nan)))
    single = a.astype(jnp.float32)
    assert bool(is_accurate_inverse(single, jnp.linalg.inv(single) + 1e-5))  # within sqrt(eps) of float32


def test_inverse_needs_pivoting_and_reports_singular_matrices():
    swap = jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    np.testing.assert_array_equal(inverse(swap), jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.5]]))
    assert not bool(jnp.all(jnp.isfinite(inverse(jnp.array([[1.0, 2.0], [2.0, 4.0]])))))


def test_lapack_inverse_pivots_batches_and_reports_singular_matrices():
    """The rare branches' inverse: exact where pivoting is needed, non-finite for a
    singular matrix, and under `vmap` each member's own inverse, in one batched call
    and member by member (a batch of 40-row matrices whose work jaxlib would split), a
    singular member spoiling no other."""
    swap = jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    np.testing.assert_array_equal(jax.jit(lapack_inverse)(swap), jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.5]]))
    assert not bool(jnp.all(jnp.isfinite(lapack_inverse(jnp.array([[1.0, 2.0], [2.0, 4.0]])))))
    for n, members in ((3, 3), (40, 4)):
        batch = jax.random.normal(jax.random.key(n), (members, n, n)).at[1].set(jnp.ones((n, n)))
        inverses = jax.jit(jax.vmap(lapack_inverse))(batch)
        assert not bool(jnp.all(jnp.isfinite(inverses[1])))
        for i in (0, 2):
            np.testing.assert_allclose(inverses[i] @ batch[i], jnp.eye(n), atol=1e-10)


def test_solve_pivots_and_reports_singular_matrices():
    """A zero diagonal block (GONZALEZ-F's Jacobians have one) needs the pivoting; a
    singular matrix gives non-finite entries, not a finite wrong answer. Above
    `UNROLL_LIMIT` the LU answers."""
    saddle = jnp.array([[2.0, 0.5, 1.0], [0.5, 3.0, -1.0], [1.0, -1.0, 0.0]])
    rhs = jnp.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(jax.jit(solve)(saddle, rhs), np.linalg.solve(saddle, rhs), rtol=1e-14)
    assert not bool(jnp.all(jnp.isfinite(solve(jnp.array([[1.0, 2.0], [2.0, 4.0]]), jnp.ones(2)))))
    large = jax.random.normal(jax.random.key(1), (UNROLL_LIMIT + 1, UNROLL_LIMIT + 1)) + 5 * jnp.eye(UNROLL_LIMIT + 1)
    ones = jnp.ones(UNROLL_LIMIT + 1)
    np.testing.assert_allclose(solve(large, ones), np.linalg.solve(large, ones), rtol=1e-12)


@given(n=st.integers(1, SPD_UNROLL_LIMIT + 3), seed=st.integers(0, 2**31 - 1))
def test_spd_solve_matches_lapack(n, seed):
    b = jax.random.normal(jax.random.key(seed), (n, n))
    a = b @ b.T + n * jnp.eye(n)
    rhs = jnp.arange(1.0, n + 1.0)
    np.testing.assert_allclose(jitted_solve_spd(a, rhs), jnp.linalg.solve(a, rhs), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [SPD_UNROLL_LIMIT + 1, UNROLL_LIMIT + 1])
def test_large_sizes_fall_back_to_lapack(n):
    a = jnp.eye(n) * 2.0
    np.testing.assert_allclose(inverse(a), 0.5 * jnp.eye(n))
    np.testing.assert_allclose(solve_spd(a, jnp.ones(n)), 0.5 * jnp.ones(n))


def test_safe_norm_has_a_zero_gradient_at_zero():
    assert float(safe_norm(jnp.zeros(3))) == 0.0
    np.testing.assert_array_equal(jax.grad(safe_norm)(jnp.zeros(3)), jnp.zeros(3))
    np.testing.assert_allclose(safe_norm(jnp.array([3.0, 4.0])), 5.0)


def _spd_family(n, seed):
    """A symmetric positive definite a(s) and a right-hand side b(s), smooth in s."""
    b0 = jax.random.normal(jax.random.key(seed), (n, n))
    b1 = jax.random.normal(jax.random.key(seed + 1), (n, n))

    def a(s):
        root = b0 + jnp.sin(s) * b1
        return root @ root.T + n * jnp.eye(n)

    return a, lambda s: jnp.cos(s * jnp.arange(1.0, n + 1.0))


@pytest.mark.parametrize("n, seed", [(1, 0), (4, 1), (SPD_UNROLL_LIMIT, 2), (SPD_UNROLL_LIMIT + 2, 3)])
def test_spd_solve_derivatives_match_lapack_solve(n, seed):
    """First and second derivatives, forward and reverse, in the matrix and the
    right-hand side (a vector and a matrix of them), against those of
    `jnp.linalg.solve`."""
    a, b = _spd_family(n, seed)
    weights = jnp.linspace(-1.0, 2.0, n)

    def scalar(solve, matrix_rhs):
        def f(s):
            rhs = jnp.stack([b(s), b(2 * s)], axis=1) if matrix_rhs else b(s)
            return jnp.sum(weights @ solve(a(s), rhs))

        return f

    for matrix_rhs in (False, True):
        ours, lapack = scalar(solve_spd, matrix_rhs), scalar(jnp.linalg.solve, matrix_rhs)
        for derivative in (jax.grad, jax.jacfwd, lambda f: jax.grad(jax.grad(f)), lambda f: jax.jacfwd(jax.grad(f))):
            # Jitted: evaluated eagerly, each derivative compiles its operations one by one.
            np.testing.assert_allclose(
                jax.jit(derivative(ours))(0.3), jax.jit(derivative(lapack))(0.3), rtol=1e-10, atol=1e-12
            )


def _traced_size(f, *x) -> int:
    """Operations in the program JAX hands to XLA for `f`, before XLA simplifies it."""
    return jax.jit(f).lower(*x).as_text().count("stablehlo.")


def test_spd_solve_is_differentiated_by_one_more_solve():
    """A derivative traces one more elimination with the same matrix, not the
    derivative of every step of it: the second derivative of $p^Ta(s)^{-1}p$ (what a
    Hamiltonian's chord matrix differentiates) within six solves' size, where
    differentiating the elimination itself takes eleven."""
    n = 6
    a, _ = _spd_family(n, 3)
    p = jnp.arange(1.0, n + 1.0)
    solve_size = _traced_size(lambda s: solve_spd(a(s), p), 0.3) - _traced_size(a, 0.3)
    assert 6 * solve_size > _traced_size(jax.jacfwd(jax.grad(lambda s: p @ solve_spd(a(s), p))), 0.3)


def _lapack_batches(function, *operands) -> list[int]:
    """The number of matrices in each LAPACK call of `function`'s compiled program that
    holds more than one (the product of the batch axes of its first result)."""
    text = jax.jit(function).lower(*operands).compile().as_text()
    batches = []
    for line in text.splitlines():
        if "custom-call(" in line and 'custom_call_target="lapack' in line:
            dims = re.search(r"f(?:32|64)\[([\d,]*)\]", line.split("custom-call")[0]).group(1).split(",")
            batch = int(np.prod([int(d) for d in dims[:-2]])) if len(dims) > 2 else 1
            if batch > 1:
                batches.append(batch)
    return batches


def test_lapack_batches_stay_below_the_work_jaxlib_splits():
    """Under `vmap`, LAPACK is called on a batch only where the batch's work is below
    `LAPACK_SPLIT_WORK` (`lapack_unbatched`: jaxlib's kernels split larger batches over
    XLA's thread pool, which can hang it): 40-row matrices ($40^3 = 64000$ flops a
    factorisation or solve) in batches of 3 keep one call, in batches of 4 and 7 are
    called in batches of 3 (and the one left over alone), a batch of right-hand sides
    for one matrix becomes the columns or rows of one call; nested `vmap`s count both
    batches. The values are those of the calls made one by one, and derivatives those
    of jax's own routines."""
    n = 40
    assert 3 * n**3 < LAPACK_SPLIT_WORK <= 4 * n**3
    keys = jax.random.split(jax.random.key(3), 3)
    a = jax.random.normal(keys[0], (7, n, n)) + 2 * n**0.5 * jnp.eye(n)
    spd = a @ jnp.swapaxes(a, 1, 2) + jnp.eye(n)
    b = jax.random.normal(keys[1], (7, n))
    columns = jax.random.normal(keys[2], (7, n, n))
    triangular = {
        "left, upper": dict(left_side=True, lower=False),
        "left, lower, transposed": dict(left_side=True, lower=True, transpose_a=True),
        "right, upper": dict(left_side=False, lower=False),
    }
    cases = {
        "solve_spd": (solve_spd, spd, b),
        "solve": (solve, a, b),
        **{
            f"triangular_solve {name}": (
                lambda m, r, flags=flags: triangular_solve(m, r, **flags),
                a,
                columns if flags["left_side"] else jnp.swapaxes(columns, 1, 2),
            )
            for name, flags in triangular.items()
        },
    }
    for name, (function, matrices, rhs) in cases.items():
        for members in (3, 4, 7):
            ms, rs = matrices[:members], rhs[:members]
            one_by_one = jnp.stack([function(m, r) for m, r in zip(ms, rs)])
            batched = jax.vmap(function)
            np.testing.assert_allclose(batched(ms, rs), one_by_one, rtol=1e-12, atol=1e-12, err_msg=name)
            assert set(_lapack_batches(batched, ms, rs)) == {3}, (name, members)
        one_matrix = jax.vmap(function, in_axes=(None, 0))
        expected = jnp.stack([function(matrices[0], r) for r in rhs])
        np.testing.assert_allclose(one_matrix(matrices[0], rhs), expected, rtol=1e-12, atol=1e-12, err_msg=name)
        assert _lapack_batches(one_matrix, matrices[0], rhs) == [], name
    batched_inverse = jax.vmap(inverse)
    np.testing.assert_allclose(batched_inverse(a), jnp.linalg.inv(a), rtol=1e-12, atol=1e-12)
    assert set(_lapack_batches(batched_inverse, a)) == {3}
    # Two batches of 2, 4 members in all: called in batches of at most 2.
    nested = jax.vmap(jax.vmap(solve))
    pairs, pair_rhs = a[:4].reshape(2, 2, n, n), b[:4].reshape(2, 2, n)
    np.testing.assert_allclose(nested(pairs, pair_rhs), jnp.linalg.solve(pairs, pair_rhs[..., None])[..., 0], rtol=1e-12)
    assert max(_lapack_batches(nested, pairs, pair_rhs)) == 2
    # One batch of 2 in a batch of 1: one call on both.
    assert max(_lapack_batches(nested, a[:2].reshape(1, 2, n, n), b[:2].reshape(1, 2, n))) == 2
    # Derivatives through the linear-solve rules, against jax's own routines.
    loss = lambda solver: lambda m, r: jnp.sum(jnp.sin(solver(m, r)))
    for ours, theirs in (
        (solve, jnp.linalg.solve),
        (
            lambda m, r: triangular_solve(m, r, left_side=True, lower=False),
            lambda m, r: jax.lax.linalg.triangular_solve(m, r, left_side=True, lower=False),
        ),
    ):
        rhs = b[0] if ours is solve else columns[0]
        for argument in (0, 1):
            np.testing.assert_allclose(
                jax.grad(loss(ours), argument)(a[0], rhs), jax.grad(loss(theirs), argument)(a[0], rhs), rtol=1e-10
            )


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("n", [3, 8, 9, 13, 26, 40])
def test_row_blocks_cover_the_matrix_in_small_blocks(n, dtype):
    """`row_blocks` splits a matrix into blocks of consecutive rows of at most
    `SEQUENTIAL_BYTES` each where that takes at most `ROW_BLOCK_LIMIT` blocks, and
    `blocked_product` of the blocks with a vector is the matrix's product."""
    matrix = jax.random.normal(jax.random.key(n), (n, n), dtype=dtype)
    vector = jax.random.normal(jax.random.key(n + 1), (n,), dtype=dtype)
    blocks = row_blocks(matrix)
    np.testing.assert_array_equal(jnp.concatenate(blocks), matrix)
    itemsize = jnp.dtype(dtype).itemsize
    fits = n * n * itemsize <= SEQUENTIAL_BYTES
    splits = -(-n // max(1, SEQUENTIAL_BYTES // (n * itemsize))) <= ROW_BLOCK_LIMIT
    if fits or not splits:
        assert len(blocks) == 1
    else:
        assert len(blocks) > 1 and all(block.size * itemsize <= SEQUENTIAL_BYTES for block in blocks)
    tolerance = 1e-12 if dtype == jnp.float64 else 1e-5
    np.testing.assert_allclose(blocked_product(blocks, vector), np.asarray(matrix) @ np.asarray(vector), rtol=tolerance, atol=tolerance * n)


def test_spd_solve_under_vmap_eliminates_once_with_the_batch_as_columns():
    """Under `vmap` with one matrix and a batch of right-hand sides (a vector or a
    matrix each), `solve_spd`'s unrolled elimination runs once on the batch as more
    columns, with the values of the solves one by one, also inside a second `vmap`
    that batches the matrix too; no array of the program is then larger than one
    matrix with its columns."""
    n = 5
    keys = jax.random.split(jax.random.key(7), 3)
    a = jax.random.normal(keys[0], (2, n, n))
    spd = a @ jnp.swapaxes(a, 1, 2) + jnp.eye(n)
    vectors = jax.random.normal(keys[1], (2, 3, n))
    matrices = jax.random.normal(keys[2], (2, 3, n, 2))
    for rhs in (vectors, matrices):
        one_by_one = jnp.stack([jnp.stack([jnp.linalg.solve(m, r) for r in rs]) for m, rs in zip(spd, rhs)])
        over_rhs = jax.jit(jax.vmap(solve_spd, in_axes=(None, 0)))
        np.testing.assert_allclose(over_rhs(spd[0], rhs[0]), one_by_one[0], rtol=1e-12, atol=1e-12)
        both = jax.jit(jax.vmap(jax.vmap(solve_spd, in_axes=(None, 0))))
        np.testing.assert_allclose(both(spd, rhs), one_by_one, rtol=1e-12, atol=1e-12)
        folded = n * (n + 3 * (rhs[0, 0].size // n))
        assert _largest_array(over_rhs, spd[0], rhs[0]) <= folded
        # Two matrices, each with its three right-hand sides folded (5 x 8 or 5 x 11):
        # eliminated one after the other, as together they would exceed SEQUENTIAL_BYTES.
        assert 2 * 8 * folded > SEQUENTIAL_BYTES >= 8 * folded
        assert _largest_array(both, spd, rhs) * 8 <= SEQUENTIAL_BYTES


def _largest_array(function, *operands) -> int:
    """The most elements of a float64 array in `function`'s compiled program."""
    return max(
        int(np.prod([int(d) for d in dims.split(",") if d]))
        for dims in re.findall(r"f64\[([\d,]*)\]", function.lower(*operands).compile().as_text())
    )


@pytest.mark.parametrize("dtype, tolerance", [(jnp.float64, 1e-7), (jnp.float32, 3e-3)])
@pytest.mark.parametrize("one_at_a_time", [False, True])
def test_jacobian_by_differences_is_the_jacobian_to_the_root_of_eps(dtype, tolerance, one_at_a_time):
    """Forward differences against the Jacobian by autodiff, at a point with entries of
    sizes 1e-3 to 1e4 (the step follows each entry's size): within a few sqrt(eps)
    relative to the Jacobian's size, in float64 and float32, batched and a column at a
    time; and not equal to it (they are differences). The function is in the program
    once (its sine once in the traced graph), its value at x one of the n + 1."""
    def function(x):
        return jnp.stack([jnp.sin(x[0]) * x[1], x[1] ** 2 + jnp.exp(1e-4 * x[2]), x[0] * x[2] * 1e-4, jnp.cos(x[3])])

    x = jnp.asarray([1e-3, 0.7, 1e4, -2.0], dtype=dtype)
    exact = jax.jacfwd(function)(x)
    differenced = jax.jit(lambda x: jacobian_by_differences(function, x, one_at_a_time))(x)
    assert differenced.dtype == dtype and differenced.shape == (4, 4)
    scale = float(jnp.max(jnp.abs(exact)))
    error = float(jnp.max(jnp.abs(differenced - exact)))
    assert error <= tolerance * scale, (error, scale)
    assert error > 0
    graph = str(jax.make_jaxpr(lambda x: jacobian_by_differences(function, x, one_at_a_time))(x))
    assert graph.count(" sin ") == 1, graph


def test_jacobian_by_differences_traces_a_function_of_known_size_once():
    """A column at a time, the loop's carry needs the function's size: given as `rows`,
    the function is traced once (for the loop) and the Jacobian is the same; without
    it, once more for its shape."""
    traces = []

    def function(x):
        traces.append(x)
        return jnp.stack([jnp.sin(x[0]) * x[1], x[1] ** 2 + x[2], x[0] * x[2]])

    x = jnp.asarray([0.3, 0.7, -1.2])
    found = jacobian_by_differences(function, x, one_at_a_time=True)
    assert len(traces) == 2
    traces.clear()
    given = jacobian_by_differences(function, x, one_at_a_time=True, rows=3)
    assert len(traces) == 1
    np.testing.assert_array_equal(given, found)

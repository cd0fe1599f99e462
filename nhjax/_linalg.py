"""Small dense linear algebra written out in `jax.numpy` operations.

The matrices inside a step are tiny (the metric, the Gram matrix of a frame: sizes 1 to
~30). For these, a LAPACK call costs more in dispatch than in
arithmetic, cannot be constant-folded when its input is constant (a constant metric),
and under `vmap` becomes a loop of calls. Elimination unrolled over the (static) size
is a few fused vector operations per column, vectorises across a batch, and is
differentiable like any other `jax.numpy` code. Above `UNROLL_LIMIT` (for symmetric
positive definite solves `SPD_UNROLL_LIMIT`) the LAPACK routines are used, never on a
batch that jaxlib would split over XLA's thread pool (`lapack_unbatched`).
"""

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Bool, Float


UNROLL_LIMIT = 16
# Symmetric positive definite solves are unrolled to a smaller size: they sit inside
# a Hamiltonian with a metric that depends on q, so a step's program holds many of
# them (each derivative of H adds one), and from n = 8 on their unrolled eliminations
# cost more to run, and far more to compile, than LAPACK's Cholesky solve
# (`benchmarks/scaling.py --family trailers`).
SPD_UNROLL_LIMIT = 7
PRODUCT_LIMIT = 32
# jaxlib's CPU LAPACK kernels split a batched call over XLA's intra-op thread pool
# where the batch's estimated flops reach this (its `kMinWorkPerTask`, jaxlib 0.10.2);
# `lapack_unbatched` keeps every batched call below it.
LAPACK_SPLIT_WORK = 200_000
# Matrix products of tiny matrices are broadcasts up to this size (`matrix_product`).
MATRIX_PRODUCT_LIMIT = 8
# XLA:CPU runs the operations of a computation (a loop's body, a branch) one after
# another only where every array they read or write, its nested computations' included,
# holds at most this many bytes; otherwise it hands them to its thread pool, whose
# scheduling costs more than the tiny operations of an iteration do. A single larger
# array in a chord iteration's body puts every operation of the body on the pool:
# Euler's disk stepped 1.4 to 3 times slower so.
SEQUENTIAL_BYTES = 512
# A batch of at most this many small eliminations whose batched arrays would not be
# small is eliminated member by member (`_eliminate_spd_folded`).
MEMBERS_UNROLLED = 4
# At most this many blocks in `row_blocks`.
ROW_BLOCK_LIMIT = 16


def lapack_unbatched(
    routine: Callable[..., Any],
    work: Callable[..., int],
    fold: str | None = None,
    members: int = 1,
    batch_dims: tuple[int, ...] | None = None,
) -> Callable[..., Any]:
    """`routine` (one of jax's LAPACK routines, its first operand a matrix), which under
    `vmap` never reaches LAPACK as a batch whose work jaxlib would split over XLA's
    intra-op thread pool (`LAPACK_SPLIT_WORK`): `work(*shapes)` bounds the flops of one
    LAPACK call of `routine` on one member, from the operands' own shapes (their batch
    axes stripped). Where the batch's work stays below it the call stays batched (and
    a further `vmap` batches it again, with the work of both batches counted:
    `members`, `batch_dims`); above it, where only the right-hand side `b` (the second
    operand) is batched, its batch becomes more columns (`fold="columns"`, for
    $ax = b$) or rows (`fold="rows"`, for $xa = b$) of one call; otherwise the batch is
    called in parts, each as many members as stay below the bound (`lax.map` over
    parts, the members left over in one more call), or one member at a time where one
    alone reaches it.

    Why: a kernel that splits its batch schedules the parts on the pool and the thread
    that made the call waits for them. Where every thread of the pool does so at once
    (two batched calls in one step's program on a machine of two cores), the parts
    never run and the program hangs (jaxlib 0.10.2). It did for the energy-preserving
    collocation's stages on a tractor pulling 57 or more trailers (matrices of 58 to 64
    rows), and for GONZALEZ-R's exact chord matrix on one with 29 trailers, whose
    $N + 1 = 35$ residuals at once hold batched Cholesky factorisations and triangular
    solves of $30 \times 30$ matrices (`benchmarks/scaling.py --family trailers` hung
    there in three runs of three while the bound was on matrices of 32 rows).
    Called on one member, a routine runs on its caller's thread. A batch below the
    bound keeps its one call: members called one at a time made a vmapped batch of 32
    tractors with 5 trailers 1.45 times slower, and the collocation's stages on 13
    trailers 1.2 times; above the bound, parts keep most of that saving. Evaluated
    only: the callers take derivatives from a rule around it
    (`jax.lax.custom_linear_solve`, `nhjax._householder`'s closed form) or cut them."""

    @jax.custom_batching.custom_vmap
    def unbatched(*operands):
        return routine(*operands)

    @unbatched.def_vmap
    def _batched(axis_size, in_batched, *operands):
        dims = batch_dims or (0,) * len(operands)
        shapes = [jnp.shape(x)[d + batched :] for x, d, batched in zip(operands, dims, in_batched)]
        if axis_size * members * work(*shapes) < LAPACK_SPLIT_WORK:
            in_axes = tuple(0 if batched else None for batched in in_batched)
            inner = lapack_unbatched(
                jax.vmap(routine, in_axes=in_axes),
                work,
                members=axis_size * members,
                batch_dims=tuple(d + batched for d, batched in zip(dims, in_batched)),
            )
            values = inner(*operands)
            return values, jax.tree.map(lambda _: True, values)
        if fold is not None and members == 1 and not in_batched[0]:
            a, b = operands
            if fold == "columns":
                return _batch_as_columns(unbatched, a, b), True
            return unbatched(a, b.reshape(-1, b.shape[-1])).reshape(b.shape), True
        per_member = tuple(
            x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))) for x, batched in zip(operands, in_batched)
        )
        # As many members a call as keep its work below the bound (none where one does not).
        per_call = (LAPACK_SPLIT_WORK - 1) // (members * work(*shapes))
        values = lax.map(lambda member: unbatched(*member), per_member, batch_size=per_call if per_call > 1 else None)
        return values, jax.tree.map(lambda _: True, values)

    return unbatched


def _columns(shape: tuple[int, ...]) -> int:
    """The columns of a right-hand side of this (unbatched) shape: 1 for a vector."""
    return shape[-1] if len(shape) >= 2 else 1


def _solve_work(a: tuple[int, ...], b: tuple[int, ...]) -> int:
    """An LU (or Cholesky) factorisation of `a` and triangular solves with `b`'s
    columns: jaxlib's estimates $n^3$ and $n^2c$ for each call."""
    n = a[-1]
    return max(n**3, n * n * _columns(b))


def _inverse_work(a: tuple[int, ...]) -> int:
    """An LU factorisation of `a` and triangular solves with its $n$ columns: $n^3$
    each."""
    return a[-1] ** 3


def _batch_as_columns(
    solve: Callable[[Array, Array], Array], a: Float[Array, "n n"], b: Float[Array, "batch n *k"]
) -> Array:
    """`solve(a, member)` for every member of the batch `b` (its first axis), from one
    call with the members as more columns of the right-hand side."""
    columns = solve(a, jnp.moveaxis(b, 0, -1).reshape(b.shape[1], -1))
    return jnp.moveaxis(columns.reshape(*b.shape[1:], b.shape[0]), -1, 0)


_cholesky_solve = lapack_unbatched(lambda a, b: jsl.cho_solve(jsl.cho_factor(a), b), _solve_work, fold="columns")
_lu_solve = lapack_unbatched(jnp.linalg.solve, _solve_work, fold="columns")
_lapack_inverse = lapack_unbatched(jnp.linalg.inv, _inverse_work)


def _triangular_work(a: tuple[int, ...], b: tuple[int, ...]) -> int:
    """jaxlib's estimate for a triangular solve with the rows and columns of `b`."""
    rows, columns = (b[-2], b[-1]) if len(b) >= 2 else (b[-1], 1)
    return rows * columns * a[-1]


@functools.cache
def _triangular_routine(left_side: bool, lower: bool, transpose_a: bool) -> Callable[..., Any]:
    return lapack_unbatched(
        functools.partial(lax.linalg.triangular_solve, left_side=left_side, lower=lower, transpose_a=transpose_a),
        _triangular_work,
        fold="columns" if left_side else "rows",
    )


def triangular_solve(
    a: Float[Array, "k k"], b: Float[Array, "..."], *, left_side: bool, lower: bool, transpose_a: bool = False
) -> Array:
    """`jax.lax.linalg.triangular_solve` (of `a`'s lower or upper triangle), never called
    on a batch (`lapack_unbatched`), differentiated as a linear solve
    (`jax.lax.custom_linear_solve`): by more solves with the triangle and its
    transpose."""
    triangle = jnp.tril(a) if lower else jnp.triu(a)
    operator = triangle.T if transpose_a else triangle

    def matvec(x):
        return operator @ x if left_side else x @ operator

    return lax.custom_linear_solve(
        matvec,
        b,
        solve=lambda _, rhs: _triangular_routine(left_side, lower, transpose_a)(a, rhs),
        transpose_solve=lambda _, rhs: _triangular_routine(left_side, lower, not transpose_a)(a, rhs),
    )


def solve_spd(a: Float[Array, "n n"], b: Float[Array, "n *k"]) -> Float[Array, "n *k"]:
    r"""$a^{-1}b$ for symmetric positive definite `a`: up to `SPD_UNROLL_LIMIT` by
    Gauss--Jordan elimination without pivoting (stable for SPD matrices: the pivots are
    ratios of leading principal minors, all positive), above it by LAPACK's Cholesky
    solve.

    Differentiated as a linear solve (`jax.lax.custom_linear_solve`):
    $d(a^{-1}b) = a^{-1}(db - da\,a^{-1}b)$, one more solve with the same matrix,
    transposed by itself since `a` is symmetric; not by differentiating each step of
    the elimination, which would grow the traced graph several times over (a metric's
    inverse inside a Hamiltonian is differentiated twice for a chord matrix)."""
    return lax.custom_linear_solve(
        lambda x: a @ x, b, solve=lambda _, rhs: _eliminate_spd_folded(a, rhs), symmetric=True
    )


@jax.custom_batching.custom_vmap
def _eliminate_spd_folded(a: Float[Array, "n n"], b: Float[Array, "n *k"]) -> Float[Array, "n *k"]:
    r"""`_eliminate_spd`, which under `vmap` with only the right-hand side batched (one
    metric, several momenta: the velocities at $X\rho$ and at the rows of $A$ in
    `nhjax._reduced.momentum_by_projection`, a gradient and its tangents) eliminates
    once with the batch as more columns.

    Besides doing the elimination once, this keeps the arrays small: XLA:CPU runs the
    operations of a loop body one after another only where every array they touch
    holds at most 512 bytes, and otherwise hands them to its thread pool, whose
    scheduling then costs more than tiny operations do. Three 5 x 5 eliminations of
    Euler's disk batched (5 x 6 augmented, 720 bytes) put its chord iteration on the
    pool; folded (5 x 8) they do not. For the same reason a batch of a few matrices
    (`MEMBERS_UNROLLED`: the stages of a collocation step), small themselves but
    whose batched eliminations would exceed `SEQUENTIAL_BYTES`, is eliminated member by
    member."""
    return _eliminate_spd(a, b)


@_eliminate_spd_folded.def_vmap
def _eliminate_spd_batched(axis_size, in_batched, a, b):
    a_batched, b_batched = in_batched
    if not a_batched:
        return _batch_as_columns(_eliminate_spd_folded, a, b), True
    b = b if b_batched else jnp.broadcast_to(b, (axis_size, *b.shape))
    member_bytes = a.dtype.itemsize * a.shape[-1] * (a.shape[-1] + b[0].size // a.shape[-1])
    if axis_size <= MEMBERS_UNROLLED and axis_size * member_bytes > SEQUENTIAL_BYTES >= a.nbytes:
        # A few members (the stages of a collocation step), each small enough to be
        # eliminated in sequence where the batch is not; only where the batch of
        # matrices is small itself (otherwise the body holds a large array anyway).
        return jnp.stack([_eliminate_spd_folded(a[i], b[i]) for i in range(axis_size)]), True
    return jax.vmap(_eliminate_spd)(a, b), True


# The eliminations are jitted: traced once per shape however often a step calls them
# (`nhjax._user_function` says why that counts).
@jax.jit
def _eliminate_spd(a: Float[Array, "n n"], b: Float[Array, "n *k"]) -> Float[Array, "n *k"]:
    n = a.shape[0]
    if n > SPD_UNROLL_LIMIT:
        return _cholesky_solve(a, b)
    vector = b.ndim == 1
    augmented = jnp.concatenate([a, b[:, None] if vector else b], axis=1)
    for j in range(n):
        row = augmented[j] / augmented[j, j]
        augmented = (augmented - jnp.outer(augmented[:, j], row)).at[j].set(row)
    solution = augmented[:, n:]
    return solution[:, 0] if vector else solution


@functools.partial(jax.jit, static_argnames="pivoting")
def inverse(a: Float[Array, "n n"], pivoting: bool = True) -> Float[Array, "n n"]:
    """$a^{-1}$ by Gauss--Jordan elimination, with partial pivoting (rows swapped by a
    gather per column), for a nonsingular `a`; a singular one gives non-finite entries.

    `pivoting=False`: a few fused vector operations per column, without the search and
    the gather. Stable for a matrix diagonally dominant by rows or by columns
    (`is_diagonally_dominant`), whose pivots stay away from zero (growth factor at most
    2: Wilkinson; Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed.,
    Thm. 9.9 and §14.4); otherwise a pivot may vanish, and the entries are then
    non-finite or wrong. Above `UNROLL_LIMIT`, LAPACK's, never called on a batch
    (`lapack_unbatched`)."""
    n = a.shape[0]
    if n > UNROLL_LIMIT:
        return _lapack_inverse(a)
    # The two halves of the augmented matrix [a | I] are eliminated side by side, not
    # joined: each is n x n, small enough for XLA:CPU to run a step's operations one
    # after another up to n = 8 (`SEQUENTIAL_BYTES`), where [a | I] is so only to n = 5.
    left, right = a, jnp.eye(n, dtype=a.dtype)
    rows = jnp.arange(n)
    for j in range(n):
        if pivoting:
            pivot = j + jnp.argmax(jnp.abs(left[j:, j]))
            order = jnp.where(rows == j, pivot, jnp.where(rows == pivot, j, rows))
            left, right = left[order], right[order]
        multipliers, pivot_value = left[:, j], left[j, j]
        row_left, row_right = left[j] / pivot_value, right[j] / pivot_value
        left = (left - jnp.outer(multipliers, row_left)).at[j].set(row_left)
        right = (right - jnp.outer(multipliers, row_right)).at[j].set(row_right)
    return right


def lapack_inverse(a: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """$a^{-1}$ by LAPACK's LU with partial pivoting at any size, never called on a batch
    of large matrices (`lapack_unbatched`); a singular `a` gives non-finite entries.
    For branches that rarely run (`nhjax._rare_branch.rarely`): there the program's
    size counts, not the call's dispatch, and the library call is a few instructions
    where `inverse` unrolls $n$ pivot searches and gathers (about 600 instructions of
    Euler's disk's GONZALEZ-R program, $n = 8$)."""
    return _lapack_inverse(a)


def solve(a: Float[Array, "n n"], b: Float[Array, " n"]) -> Float[Array, " n"]:
    r"""$a^{-1}b$ for a general nonsingular `a`: up to `UNROLL_LIMIT` by the pivoted
    `inverse` times $b$, which reverse mode transposes into a product with the
    inverse's transpose; above, by LAPACK's LU. A singular `a` gives non-finite entries.

    For the small systems of a step (the Jacobian of a root, for its derivatives),
    LAPACK's LU is a factorisation, two triangular solves and, transposed, a sort that
    turns its pivots into a permutation: separate library calls on XLA:CPU, which cost
    more than the arithmetic (`benchmarks/gradients.py`). The inverse's rounding is a
    solve's for a well-conditioned `a`. Above `UNROLL_LIMIT`, LAPACK's LU never called on
    a batch (`lapack_unbatched`), differentiated as a linear solve
    (`jax.lax.custom_linear_solve`), by more solves with `a` and its transpose."""
    if a.shape[0] > UNROLL_LIMIT:
        return lax.custom_linear_solve(
            lambda x: a @ x,
            b,
            solve=lambda _, rhs: _lu_solve(a, rhs),
            transpose_solve=lambda _, rhs: _lu_solve(a.T, rhs),
        )
    return inverse(a) @ b


def is_accurate_inverse(a: Float[Array, "n n"], inverse_of_a: Float[Array, "n n"]) -> Bool[Array, ""]:
    r"""Whether $\max|a\,x - I| \le \sqrt{\varepsilon}$ for `inverse_of_a` $= x$
    (false where it is not finite)."""
    identity = jnp.eye(a.shape[0], dtype=a.dtype)
    return jnp.max(jnp.abs(a @ inverse_of_a - identity)) <= jnp.sqrt(jnp.finfo(a.dtype).eps)


def is_diagonally_dominant(a: Float[Array, "n n"]) -> Bool[Array, ""]:
    """Whether `a` is strictly diagonally dominant by rows or by columns."""
    magnitudes = jnp.abs(a)
    diagonal = jnp.diagonal(magnitudes)
    by_rows = jnp.all(2 * diagonal > jnp.sum(magnitudes, axis=1))
    by_columns = jnp.all(2 * diagonal > jnp.sum(magnitudes, axis=0))
    return by_rows | by_columns


def product(a: Float[Array, "*m k"], b: Float[Array, "k *n"]) -> Array:
    """`a @ b` where `a` or `b` is a vector, for the sizes inside a step, as a broadcast
    multiply and a sum over the shared axis: XLA:CPU fuses that with the operations
    around it, where a dot is a library call of its own. (Matrix products stay dots:
    as broadcasts they made vmapped batches slower; `benchmarks/gonzalez_r.py`.) Above
    `PRODUCT_LIMIT` along some axis, `@`."""
    if a.ndim == 2 and b.ndim == 2:
        raise ValueError("product is for a matrix and a vector; use @ for two matrices.")
    if max(a.shape + b.shape) > PRODUCT_LIMIT:
        return a @ b
    if b.ndim == 1:
        return jnp.sum(a * b, axis=-1)
    return jnp.sum(a[:, None] * b, axis=0)


def matrix_product(a: Float[Array, "*b m k"], b: Float[Array, "*b k n"]) -> Float[Array, "*b m n"]:
    """`a @ b` (batched), for tiny matrices (every axis at most `MATRIX_PRODUCT_LIMIT`)
    as a broadcast multiply and a sum, which XLA:CPU fuses with what is around it. Above
    that, `@`: the broadcast's $mkn$ products cost more than the dot's call (the
    chord matrices of `nhjax.EnergyPreservingCollocation`: faster with $N = 5$ unknowns
    a stage, slower with $N = 13$)."""
    if max(a.shape[-2:] + b.shape[-2:]) > MATRIX_PRODUCT_LIMIT:
        return jnp.matmul(a, b)
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def jacobian_by_columns(
    function: Callable[[Float[Array, " n"]], Float[Array, " m"]], x: Float[Array, " n"]
) -> Float[Array, "m n"]:
    """The Jacobian of `function` at `x`, one column at a time (`jax.lax.map` of its
    linearisation over the unit vectors): the arrays are those of one tangent, where
    `jax.jacfwd`'s are those of all n at once, small enough for XLA:CPU to run the
    operations around them in sequence (`SEQUENTIAL_BYTES`), at the price of n
    trips through a loop."""
    linear = jax.linearize(function, x)[1]
    return lax.map(linear, jnp.eye(x.shape[0], dtype=x.dtype)).T


def jacobian_by_differences(
    function: Callable[[Float[Array, " n"]], Float[Array, " m"]],
    x: Float[Array, " n"],
    one_at_a_time: bool = False,
    rows: int | None = None,
) -> Float[Array, "m n"]:
    r"""The Jacobian of `function` at `x` by forward differences,
    $(f(x + \delta_je_j) - f(x))/\delta_j$ with
    $\delta_j = \sqrt\varepsilon\,\max(|x_j|, 1)$ (`x` in units in which 1 is its
    natural size), taken as the difference of the perturbed and the unperturbed
    $x_j$ as they are stored: its error is $O(\sqrt\varepsilon)$ relative to $f$'s
    variation (truncation and rounding balanced; Dennis & Schnabel, *Numerical
    Methods for Unconstrained Optimization and Nonlinear Equations*, §5.4). For a
    chord matrix, where that error changes the iteration's contraction by as
    little and not its root, and where $f$'s own derivatives (through a QR, say)
    would make a program several times the size of $f$'s.

    $n + 1$ evaluations of $f$: batched (`jax.vmap`), or with `one_at_a_time` in a
    loop of $n + 1$ trips whose arrays are those of one evaluation and the $n$ columns
    (as `jacobian_by_columns`). Either way $f$ is traced once, its value at `x` the
    first of the $n + 1$ (`x` moved by zero): the program holds one copy of $f$, not
    two (GONZALEZ-R's residual on Euler's disk is some 1 500 instructions). The loop's
    carry needs $f$'s size $m$: `rows`, where the caller knows it (a chord matrix is
    square), else found by tracing $f$ once more for its shape (`jax.eval_shape`), a
    trace that costs as much as the loop's own."""
    step = jnp.sqrt(jnp.finfo(x.dtype).eps) * jnp.maximum(jnp.abs(x), 1)
    step = (x + step) - x
    n = x.shape[0]
    if not one_at_a_time:
        moves = jnp.concatenate([jnp.zeros((1, n), x.dtype), jnp.diag(step)])
        values = jax.vmap(lambda move: function(x + move))(moves)
        return ((values[1:] - values[0]) / step[:, None]).T

    def trip(j, carry):
        # Trip 0 evaluates f at x; trip j > 0 moves x_{j-1} and forms column j - 1.
        at_x, columns = carry
        k = jnp.maximum(j - 1, 0)
        value = function(x.at[k].add(jnp.where(j > 0, step[k], 0)))
        at_x = jnp.where(j == 0, value, at_x)
        return at_x, columns.at[k].set(jnp.where(j == 0, columns[k], (value - at_x) / step[k]))

    size = jax.eval_shape(function, x).shape[0] if rows is None else rows
    start = (jnp.zeros(size, x.dtype), jnp.zeros((n, size), x.dtype))
    return lax.fori_loop(0, n + 1, trip, start)[1].T


def rows_per_block(columns: int, dtype) -> int:
    """The most rows of `columns` entries of `dtype` within `SEQUENTIAL_BYTES` (at least
    one): the height of a `row_blocks` block."""
    return max(1, SEQUENTIAL_BYTES // (columns * jnp.dtype(dtype).itemsize))


def row_blocks(matrix: Float[Array, "m n"]) -> tuple[Float[Array, "r n"], ...]:
    """`matrix` as consecutive blocks of rows of at most `SEQUENTIAL_BYTES` each, for a
    matrix read in a loop's body (`blocked_product`); the whole matrix as one block
    where it is that small already, or where it would take more than
    `ROW_BLOCK_LIMIT` blocks (then its rows are long enough that the body's other
    arrays are large too)."""
    rows, columns = matrix.shape
    per_block = rows_per_block(columns, matrix.dtype)
    if per_block >= rows or -(-rows // per_block) > ROW_BLOCK_LIMIT:
        return (matrix,)
    return tuple(matrix[start : start + per_block] for start in range(0, rows, per_block))


def blocked_product(blocks: tuple[Float[Array, "r n"], ...], vector: Float[Array, " n"]) -> Float[Array, " m"]:
    """The product of the matrix whose `row_blocks` are `blocks` with `vector`."""
    if len(blocks) == 1:
        return blocks[0] @ vector
    return jnp.concatenate([block @ vector for block in blocks])


def safe_norm(v: Float[Array, " n"]) -> Float[Array, ""]:
    """|v|, with derivative 0 (not NaN) at v = 0."""
    square = v @ v
    return jnp.where(square == 0, 0.0, jnp.sqrt(jnp.where(square == 0, 1.0, square)))


def is_quadratic_form(
    function: Callable[[Float[Array, " n"]], Float[Array, ""]],
    matrix: Float[Array, "n n"],
    direction: Float[Array, " n"],
    tolerance: Callable[[Any, Any], Any],
) -> Bool[Array, ""]:
    r"""Whether $f(u) = f(0) + \tfrac12u^TSu$ for `function` $f$ and `matrix` $S$, along
    `direction` and two fixed directions, with no term linear in $u$
    ($\nabla f(0) = 0$) and $S$ symmetric positive definite; `tolerance(dtype, scale)`
    is the rounding allowed. The test of mechanical type for a Hamiltonian in $p$ and
    for a Lagrangian in $\dot q$."""
    n = direction.shape[0]
    dtype = direction.dtype
    zero = jnp.zeros_like(direction)
    base = function(zero)
    probes = jnp.stack([direction, jnp.ones_like(direction), jnp.cos(jnp.arange(n, dtype=dtype))])

    def quadratic_along(u):
        form = 0.5 * u @ matrix @ u
        value = function(u)
        return jnp.abs(value - base - form) <= tolerance(dtype, jnp.abs(value) + jnp.abs(base) + jnp.abs(form))

    quadratic = jnp.all(jax.vmap(quadratic_along)(probes))
    scale = jnp.max(jnp.abs(matrix))
    no_linear = jnp.max(jnp.abs(jax.grad(function)(zero))) <= tolerance(dtype, scale)
    symmetric = jnp.max(jnp.abs(matrix - matrix.T)) <= tolerance(dtype, scale)
    positive = jnp.all(jnp.isfinite(jnp.linalg.cholesky(matrix)))
    return quadratic & no_linear & symmetric & positive

r"""A differentiable Householder QR with explicit sign choices, and the frame of
$\mathcal{D} = \ker A(q)$ it gives (paper §3.3).

For $A^T \in \mathbb{R}^{n \times k}$ ($k \le n$), step $j$ reflects the column
$x = R^{(j)}_{j:n,j}$ onto $-s_j|x|e_1$ with the Householder vector
$\tilde w = x + s_j|x|e_1$, $w = \tilde w/|\tilde w|$, $|\tilde w|^2 = 2(|x|^2 + s_j x_1|x|)$
(Algorithm 1's first half). Then $A^T = QR$ with $Q = H_1\cdots H_k$, $H_j = I - 2w_jw_j^T$,
and the last $m = n - k$ columns of $Q$ are an orthonormal basis $X(q)$ of $\ker A(q)$.

The signs $s \in \{+1, -1\}^k$ are explicit. The stable choice $s_j = \mathrm{sign}(x_1)$
(no cancellation in $\tilde w_1$) is what `householder_signs` returns; passing the same
$s$ to every later factorisation makes $q \mapsto X(q; s)$ one smooth frame on the
neighbourhood of the first point where no $\tilde w$ vanishes, so that frames sampled at
different points of one step belong to the same basis vector fields. `jax.jacfwd`
through `householder_frame` gives $\partial X/\partial q$: this replaces the paper's
Algorithm 1 (its second half is the forward-mode derivative of its first). For a few
constraints every operation is a plain `jax.numpy` operation, differentiated step by
step; above `UNROLLED_REFLECTIONS` the factorisation is LAPACK's where the signs are
the stable ones, and the reflections are differentiated in closed form
(`_reflector_tangents`). Where only products $X^Tv$ are needed, `HouseholderFrame`
forms them from the reflectors without forming $X$ ($O(nk)$ per product instead of
$O(nmk)$ for $X$).
"""

import functools

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._linalg import lapack_unbatched, safe_norm, triangular_solve
from ._rare_branch import rarely


# Up to this many reflections the loops over them are unrolled: the fewest operations
# for the few constraints of most systems. Beyond it the factorisation is LAPACK's
# (or a `lax.scan` where a given sign is not the stable one: `_many_reflectors`), whose
# program does not grow with k, differentiated in closed form
# (`_reflector_tangents`), and products with the frame take the compact WY form
# (`_wy_factor`): unrolled, every factorisation, product and derivative of them in a
# step is k copies, and at k = 16 (n = 64 in `benchmarks/scaling.py`) they set the
# compile time; differentiated through the scan, the derivatives are k sequential
# steps forward and k again transposed, which made most of a GONZALEZ-R residual
# there.
UNROLLED_REFLECTIONS = 4


def _qr_work(a_t: tuple[int, ...]) -> int:
    """jaxlib's estimate of `geqrf`'s flops on an $n \times k$ matrix, $2nk^2$ at most."""
    n, k = a_t[-2:]
    return 2 * n * k * min(n, k)


# NumPy's "raw" QR, LAPACK's `geqrf`, never on a batch that jaxlib would split
# (`nhjax._linalg.lapack_unbatched`).
_raw_qr = lapack_unbatched(lambda a_t: jnp.linalg.qr(a_t, mode="raw"), _qr_work)


def _reflection(r, j, given_sign):
    r"""Step $j$ of the factorisation of the partly reduced `r`: the reflected `r`, and
    the unit vector $w_j$, the pivot $|\tilde w_j|/\sqrt2$, $|x_j|$ and the sign used
    (the stable one where `given_sign` is `None`)."""
    n = r.shape[0]
    index = np.arange(n) if isinstance(j, int) else jnp.arange(n)
    # Every vector at full length n, masked below the pivot rather than sliced: the
    # same arithmetic in far fewer operations (slices, pads and their derivatives'
    # scatters), which on XLA:CPU set the cost of the small factorisations here.
    column = r[:, j]
    x = jnp.where(index >= j, column, 0.0)
    leading = column[j]
    # Finite derivatives at x = 0, where the factorisation breaks down and the caller
    # reports rank deficiency.
    norm = safe_norm(x)
    sign = jnp.where(leading >= 0, 1.0, -1.0).astype(r.dtype) if given_sign is None else given_sign
    length_sq = 2 * (norm**2 + sign * leading * norm)
    length = jnp.sqrt(jnp.where(length_sq > 0, length_sq, 1.0))
    w = (x + jnp.where(index == j, sign * norm, 0.0)) / length
    # The columns before j are not read again, and column j's image is known
    # (-s_j|x|e_1): only the columns after j need the reflection, but reflecting
    # all k keeps the shapes fixed.
    r = r - 2 * jnp.outer(w, w @ r)
    return r, (w, jnp.sqrt(jnp.maximum(length_sq, 0.0) / 2), norm, sign)


# Jitted, as `_reflect` is: a step factorises at several points and differentiates the
# factorisations in several ways, and JAX then traces the body once per shape and
# reuses the trace (and its derivatives) at every call (`nhjax._user_function`).
@jax.jit
def _reflectors(a_t, signs):
    r"""The unit Householder vectors (as rows, zero above their pivot), the pivots
    $|\tilde w_j|/\sqrt2$, R's diagonal magnitudes |x_j|, and the signs used."""
    k = a_t.shape[1]
    if k > UNROLLED_REFLECTIONS:
        return _many_reflectors(a_t, signs)
    r = a_t
    outputs = []
    for j in range(k):
        r, output = _reflection(r, j, None if signs is None else signs[j])
        outputs.append(output)
    vectors, pivots, norms, used = zip(*outputs)
    return jnp.stack(vectors), jnp.stack(pivots), jnp.stack(norms), jnp.stack(used)


@jax.custom_jvp
def _many_reflectors(a_t, signs):
    """`_reflectors` beyond `UNROLLED_REFLECTIONS`, differentiated in closed form
    (`_reflector_tangents`): by LAPACK's QR (`_lapack_reflectors`), whose reflections
    are those with the stable signs; where the given `signs` are not all the stable
    ones (a step whose frame keeps its start's signs, `nhjax._reduced.ReducedSystem`,
    where a pivot's leading entry changed sign), by a scan over the reflections with
    the given signs (`rarely`: under `vmap` only where a trajectory needs it)."""
    stable = _lapack_reflectors(a_t)
    if signs is None:
        return stable
    return rarely(jnp.any(stable[3] != signs), _scanned_reflectors, stable, (a_t, signs))


def _scanned_reflectors(operands):
    """The reflections one after another with the given signs, as a scan."""
    a_t, signs = operands

    def step(r, j_and_sign):
        j, given_sign = j_and_sign
        return _reflection(r, j, given_sign)

    return lax.scan(step, a_t, (jnp.arange(a_t.shape[1]), signs))[1]


def _lapack_reflectors(a_t):
    r"""`_reflectors` with the stable signs from LAPACK's Householder QR (`geqrf`): one
    library call, where a scan over $k$ reflections runs $k$ sequential steps of a
    dozen operations each, which made most of a GONZALEZ-R residual for a tractor with
    13 trailers ($k = 14$).

    LAPACK's reflector of $x$ (`larfg`) is $H = I - \tau vv^T$, $v_1 = 1$, mapping $x$ to
    $\beta e_1$, $\beta = -\mathrm{sign}(x_1)|x|$, with $\tau = (\beta - x_1)/\beta$: the
    unit $w = s\,v/|v|$ with $s = \mathrm{sign}(x_1) = -\mathrm{sign}(\beta)$ is
    `_reflection`'s with the stable sign, and $x_1 = \beta(1 - \tau)$. Where $x$ has
    nothing below its first entry, LAPACK takes $\tau = 0$ ($H = I$, $\beta = x_1$) and
    `_reflection` the reflection along $e_1$: the same frame (a sign flip of a row
    of $R$ the frame never reads), and $w = s\,e_1$ with $s = \mathrm{sign}(\beta)$."""
    n, k = a_t.shape
    # NumPy's "raw" mode: LAPACK's packed factorisation, transposed.
    packed_t, taus = _raw_qr(a_t)
    packed = packed_t.T
    rows, columns = jnp.arange(n)[:, None], jnp.arange(k)[None, :]
    v = jnp.where(rows > columns, packed, 0.0) + (rows == columns).astype(a_t.dtype)
    beta = jnp.diagonal(packed)
    one = jnp.ones((), a_t.dtype)
    sign_of_beta = jnp.where(beta >= 0, one, -one)
    signs = jnp.where(taus == 0, sign_of_beta, -sign_of_beta)
    vectors = (signs[None, :] * v / jnp.sqrt(jnp.sum(v * v, axis=0))[None, :]).T
    norms = jnp.abs(beta)
    leading = beta * (1 - taus)
    pivots = jnp.sqrt(norms * (norms + jnp.abs(leading)))
    return vectors, pivots, norms, signs


@_many_reflectors.defjvp
def _many_reflectors_jvp(primals, tangents):
    a_t, signs = primals
    a_t_dot = tangents[0]
    outputs = _many_reflectors(a_t, signs)
    vectors, _, norms, used = outputs
    vectors_dot, pivots_dot, norms_dot = _reflector_tangents(a_t, vectors, norms, a_t_dot)
    return outputs, (vectors_dot, pivots_dot, norms_dot, jnp.zeros_like(used))


def _wy_factor(w: Float[Array, "n k"]) -> Float[Array, "k k"]:
    r"""$T$ of the compact WY form $H_1\cdots H_k = I - WT^{-1}W^T$ of the reflections
    $H_j = I - 2w_jw_j^T$ (the columns of `w`): $T = \tfrac12I + \operatorname{striu}(W^TW)$
    (Joffrain, Low, Quintana-Ortí, van de Geijn & Van Zee, "Accumulating Householder
    transformations, revisited", ACM TOMS 32 (2006) 169, the UT transform)."""
    return jnp.triu(w.T @ w, 1) + 0.5 * jnp.eye(w.shape[1], dtype=w.dtype)


def _nonzero_diagonal(a: Float[Array, "k k"]) -> Float[Array, "k k"]:
    """`a` with a zero diagonal entry replaced by 1: finite tangents where the
    factorisation breaks down (rank loss), which the caller reports."""
    diagonal = jnp.diagonal(a)
    return a + jnp.diag(jnp.where(diagonal == 0, 1.0, 0.0).astype(a.dtype))


def _reflector_tangents(a_t, vectors, norms, a_t_dot):
    r"""The tangents of the unit Householder vectors $w_j$, the pivots and $|R_{jj}|$
    along $dA^T$, in closed form: a few products of $n \times k$ and $k \times k$
    matrices and triangular solves, where differentiating the scan of $k$ reflections
    costs $k$ sequential steps forward and again transposed.

    With $Q = H_1\cdots H_k = I - WT^{-1}W^T$ (`_wy_factor`), its first $k$ columns are
    $Q_1 = E - WV$, $E = [I_k; 0]$, $V = T^{-1}W_1^T$ upper triangular ($W_1$ the top
    $k \times k$ block of $W$, lower triangular): $E - Q_1 = WV$ is an LU factorisation,
    whose factors are fixed by $Q_1$ up to the scaling of $W$'s columns (Ballard,
    Demmel, Grigori, Jacquelin, Nguyen & Solomonik, "Reconstructing Householder
    vectors from tall-skinny QR", IPDPS 2014). So:

    1. the thin QR $A^T = Q_1R$ (with R's signs those of the factorisation) gives
       $dQ_1 = dA^TR^{-1} - Q_1\,dR\,R^{-1}$ with $dR\,R^{-1} = M - C$,
       $M = Q_1^TdA^TR^{-1}$, $C = \operatorname{tril}(M, -1) - \operatorname{tril}(M, -1)^T$
       (the skew $Q_1^TdQ_1$);
    2. the LU factorisation's derivative: with $G = W_1^{-1}(-dQ_1)_1V^{-1}$,
       $W_1^{-1}dW_1 = \operatorname{tril}(G, -1) + \Delta$ and
       $dV\,V^{-1} = \operatorname{triu}(G) - \Delta$, so
       $dW = [W_1\operatorname{tril}(G, -1);\ -(dQ_1)_2V^{-1} - W_2\operatorname{triu}(G)]
       + W\Delta$, the diagonal $\Delta$ fixed by $w_j^Tdw_j = 0$ (unit vectors);
    3. $|R_{jj}|$ changes by $M_{jj}|R_{jj}|$, and the pivot
       $|\tilde w_j|/\sqrt2 = \sqrt2\,|R_{jj}|\,|w_{jj}|$ accordingly.

    These are the derivatives of the reflections themselves (checked against
    differentiating the unrolled reflections, `tests/test_householder.py`)."""
    k = a_t.shape[1]
    w = vectors.T
    w_top = w[:k]
    v = triangular_solve(_wy_factor(w), w_top.T, left_side=True, lower=False)
    q1 = jnp.eye(*a_t.shape, dtype=a_t.dtype) - w @ v
    r = _nonzero_diagonal(jnp.triu(q1.T @ a_t))
    a_r = triangular_solve(r, a_t_dot, left_side=False, lower=False)
    m = q1.T @ a_r
    lower = jnp.tril(m, -1)
    q1_dot = a_r - q1 @ (m - lower + lower.T)
    b_dot_v = triangular_solve(_nonzero_diagonal(v), -q1_dot, left_side=False, lower=False)
    g = triangular_solve(_nonzero_diagonal(w_top), b_dot_v[:k], left_side=True, lower=True)
    base = jnp.concatenate([w_top @ jnp.tril(g, -1), b_dot_v[k:] - w[k:] @ jnp.triu(g)])
    w_dot = base - w * jnp.sum(w * base, axis=0)
    norms_dot = jnp.diagonal(m) * norms
    diagonal, diagonal_dot = jnp.diagonal(w_top), jnp.diagonal(w_dot[:k])
    root_two = jnp.sqrt(2.0).astype(a_t.dtype)
    pivots_dot = root_two * (norms_dot * jnp.abs(diagonal) + norms * jnp.sign(diagonal) * diagonal_dot)
    return w_dot.T, pivots_dot, norms_dot


def householder_pivots(
    a_t: Float[Array, "n k"], signs: Float[Array, " k"] | None = None
) -> tuple[Float[Array, " k"], Float[Array, " k"]]:
    r"""The pivots $|\tilde w_j|/\sqrt2 = (|x_j|^2 + s_jx_{j,1}|x_j|)^{1/2}$ of the
    factorisation with sign choices `signs` (`None`: the stable ones), and
    $|x_j| = |R_{jj}|$, the distance of column $j$ from the span of the columns before
    it, which does not depend on the signs; the frame is not formed."""
    _, pivots, norms, _ = _reflectors(a_t, signs)
    return pivots, norms


def householder_signs(a_t: Float[Array, "n k"]) -> Float[Array, " k"]:
    """The stable sign choices $s_j = \\mathrm{sign}(x_1)$ for the factorisation of
    `a_t` ($+1$ where $x_1 = 0$)."""
    return _reflectors(a_t, None)[3]


class HouseholderFrame(eqx.Module):
    r"""The frame $X = H_1\cdots H_k[0; I_m]$ of $\ker A$ as its $k$ unit Householder
    vectors $w_j$ (rows of `vectors`, zero above their pivot), for products with $X$
    and $X^T$ without forming it: $Xv = H_1\cdots H_k[0; v]$ and
    $X^Tv = [0\ I_m]H_k\cdots H_1v$, $k$ reflections of a vector each, or above
    `UNROLLED_REFLECTIONS` the compact WY form $H_1\cdots H_k = I - WT^{-1}W^T$ with
    `factor` $= T$ (`_wy_factor`), formed once for every product with the frame and
    their derivatives (`None` below it)."""

    vectors: Float[Array, "k n"]
    factor: Float[Array, "k k"] | None

    def __init__(self, vectors: Float[Array, "k n"]):
        self.vectors = vectors
        self.factor = _wy_factor(vectors.T) if vectors.shape[0] > UNROLLED_REFLECTIONS else None

    @property
    def shape(self) -> tuple[int, int]:
        k, n = self.vectors.shape
        return n, n - k

    def times(self, v: Float[Array, "m *r"]) -> Float[Array, "n *r"]:
        """$Xv$, for a vector or a matrix `v`."""
        k = self.vectors.shape[0]
        x = jnp.concatenate([jnp.zeros((k, *v.shape[1:]), v.dtype), v])
        if self.factor is not None:
            return _wy_reflect(x, self.vectors, self.factor, reverse=True)
        return _reflect(x, self.vectors, _reflected, reverse=True)

    def transpose_times(self, v: Float[Array, " n"]) -> Float[Array, " m"]:
        """$X^Tv$."""
        k = self.vectors.shape[0]
        if self.factor is not None:
            return _wy_reflect(v, self.vectors, self.factor, reverse=False)[k:]
        return _reflect(v, self.vectors, _reflected_vector, reverse=False)[k:]

    def matrix(self) -> Float[Array, "n m"]:
        """$X$ itself."""
        n, m = self.shape
        return self.times(jnp.eye(m, dtype=self.vectors.dtype))


def _reflected(x, w):
    """$(I - 2ww^T)x$ for a vector or a matrix `x`."""
    return x - 2 * (jnp.outer(w, w @ x) if x.ndim == 2 else w * (w @ x))


def _reflected_vector(v, w):
    """$(I - 2ww^T)v$, grouped as $X^Tv$ has always grouped it (another grouping would
    round differently where the compiler fuses a multiply-add)."""
    return v - 2 * w * (w @ v)


@functools.partial(jax.jit, static_argnames=("reflect", "reverse"))
def _reflect(x, vectors, reflect, reverse: bool):
    r"""$H_1\cdots H_kx$ (`reverse`: the last reflection first) or $H_k\cdots H_1x$, one
    reflection (`reflect`) after another."""
    for w in reversed(list(vectors)) if reverse else vectors:
        x = reflect(x, w)
    return x


@functools.partial(jax.jit, static_argnames=("reverse",))
def _wy_reflect(x, vectors, factor, reverse: bool):
    r"""$H_1\cdots H_kx = x - WT^{-1}W^Tx$ (`reverse`) or $H_k\cdots H_1x =
    x - WT^{-T}W^Tx$, with `factor` $= T$ (`_wy_factor`): two products and a triangular
    solve, whose derivatives in the vectors are as few operations, where a scan of k
    reflections is k sequential steps, and as many again transposed."""
    w = vectors.T
    coefficients = w.T @ (x if x.ndim == 2 else x[:, None])
    solved = triangular_solve(factor, coefficients, left_side=True, lower=False, transpose_a=not reverse)
    return x - (w @ solved if x.ndim == 2 else w @ solved[:, 0])


class FormedFrame(eqx.Module):
    """A frame given as its matrix, with the products of `HouseholderFrame`: for a frame
    used many times over (a Jacobian's columns), where forming it once is cheaper
    than reflecting every column."""

    matrix_: Float[Array, "n m"]

    @property
    def shape(self) -> tuple[int, int]:
        return self.matrix_.shape

    def times(self, v: Float[Array, "m *r"]) -> Float[Array, "n *r"]:
        return self.matrix_ @ v

    def transpose_times(self, v: Float[Array, "n *r"]) -> Float[Array, "m *r"]:
        return self.matrix_.T @ v

    def matrix(self) -> Float[Array, "n m"]:
        return self.matrix_


def householder_frame_operator(a_t: Float[Array, "n k"], signs: Float[Array, " k"]) -> HouseholderFrame:
    """The frame of `householder_frame` as a `HouseholderFrame`, not formed."""
    return HouseholderFrame(_reflectors(a_t, signs)[0])


def householder_stable_frame(a_t: Float[Array, "n k"]) -> tuple[HouseholderFrame, Float[Array, " k"]]:
    """The frame of `householder_frame_operator` with the stable signs, and those signs
    (`householder_signs`), from one factorisation: with the signs it returns, the
    factorisation with given signs is this one, value for value."""
    vectors, _, _, used = _reflectors(a_t, None)
    return HouseholderFrame(vectors), used


def householder_frame(
    a_t: Float[Array, "n k"], signs: Float[Array, " k"]
) -> tuple[Float[Array, "n m"], Float[Array, " k"]]:
    r"""$X = Q_{:, k:}$, the orthonormal basis of $\ker A$ from the factorisation with
    sign choices `signs`, and $\rho_{\min} = \min_j |\tilde w_j|/\sqrt2$, which is at
    least $\min_j |R_{jj}|$: a small value relative to $|A|$ means that $A$ has (nearly)
    lost rank, or that `signs` no longer suit this point.

    Only the last $m$ columns are formed: $X = H_1 \cdots H_k [0; I_m]$.
    """
    vectors, pivots, _, _ = _reflectors(a_t, signs)
    return HouseholderFrame(vectors).matrix(), jnp.min(pivots)

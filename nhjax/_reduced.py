r"""The reduced form of a `NonholonomicSystem` on $\mathcal{D}^*$ for a Householder
frame, eqs. (PiMat), (skewMat), (eq:Htgrad): what GONZALEZ-R integrates, and what
`NonholonomicSystem.reduced`, `.to_reduced` and `.from_reduced` build on. It takes the
system as it is given (anything with the `NonholonomicSystem` methods it calls) and
imports nothing of it: the dependence runs one way, `nhjax._nonholonomic` to here.

Notation as in `nhjax._nonholonomic`: $H = \tfrac12 p^TK(q)p + V(q)$, $M = K^{-1}$,
frame $X(q; s)$ of $\ker A(q)$, $\rho = X^Tp$, $\zeta = (q, \rho)$.
"""

from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._adapted import adapted_structure
from ._dependence import evaluated_inverse_metric, velocity_dependence
from ._householder import FormedFrame, HouseholderFrame
from ._linalg import product, solve_spd


Derivative = Literal["autodiff", "central_difference"]


def check_derivative(derivative) -> None:
    """Raise a `ValueError` unless `derivative` names a way to compute dX/dq."""
    if derivative not in ("autodiff", "central_difference"):
        raise ValueError(
            f'derivative must be "autodiff" or "central_difference", got {derivative!r}.'
        )


def check_difference_step(derivative: Derivative, difference_step) -> None:
    """Raise a `ValueError` unless `difference_step` suits `derivative`: `None` or a
    positive finite scalar with `"central_difference"` (checked where it is concrete),
    `None` with `"autodiff"`, which would ignore it."""
    if difference_step is None:
        return
    if derivative != "central_difference":
        raise ValueError(
            f'difference_step is the increment of derivative="central_difference"; with '
            f"derivative={derivative!r} it would be ignored, got difference_step={difference_step!r}."
        )
    if isinstance(difference_step, jax.core.Tracer):
        return
    step = np.asarray(difference_step)
    if step.shape != () or not np.isfinite(step) or not step > 0:
        raise ValueError(f"difference_step must be a positive finite number, got {difference_step!r}.")


def momentum_in_frame(frame: HouseholderFrame, rho, metric=None):
    r"""Eq. (ptoptilde) in a given frame $X$ and a constant metric $M$:
    $p = MX(X^TMX)^{-1}\rho$, and $y = (X^TMX)^{-1}\rho$, the velocity in the frame
    ($\partial H/\partial p = Xy$). `metric=None` stands for $M = I$, where the
    orthonormal frame gives $y = \rho$ and $p = X\rho$ (to rounding; exactly what the
    formula is then taken to mean)."""
    if metric is None:
        return frame.times(rho), rho
    matrix = frame.matrix()
    weighted = metric @ matrix
    y = solve_spd(matrix.T @ weighted, rho)
    return weighted @ y, y


def momentum_by_projection(system, q, frame: HouseholderFrame, rho, args):
    r"""Eq. (ptoptilde) where $M$ depends on $q$, without forming $M$: the $p$ and $y$
    of `momentum_in_frame`, from products with $K = M^{-1}$ alone.

    $p = MX(X^TMX)^{-1}\rho$ is the momentum with $X^Tp = \rho$ whose velocity $Kp$
    lies in $\mathcal{D} = \ker A$. As the columns of $X$ are orthonormal and
    orthogonal to those of $A^T$, these two conditions say

    $$p = X\rho + A^T\lambda, \qquad AKA^T\lambda = -AKX\rho, \qquad
      y = X^TKp:$$

    one $k \times k$ solve in place of an $n \times n$ one (for $MX$) and an
    $m \times m$ one (for $y$). The products $Kw$, for $w = X\rho$ and the columns of
    $A^T$, are velocities $\partial H/\partial p$ at $p = w$, as $H$ is of mechanical
    type (quadratic in $p$ with no linear term, checked at the start of a run): $k + 1$
    gradients, where `NonholonomicSystem.inverse_metric` differentiates $n$ of them.

    $y$ is $\partial\mathcal{H}/\partial\rho$: with $p = P\rho$,
    $P = (I - A^T(AKA^T)^{-1}AK)X$, $\partial\mathcal{H}/\partial\rho = P^TKp =
    X^TKp - X^TKA^T(AKA^T)^{-1}AKp = X^TKp$, since $AKp = 0$. Programs differentiated
    through a step (GONZALEZ-R's derivatives) are smaller this way than through the
    two unrolled solves."""
    a = system.constraints(q, args)
    along_frame = frame.times(rho)
    velocity = lambda w: system.velocity(q, w, args)  # noqa: E731
    products = jax.vmap(velocity)(jnp.concatenate([along_frame[None], a], axis=0))
    k_along_frame, k_a_t = products[0], products[1:].T
    multiplier = -solve_spd(a @ k_a_t, a @ k_along_frame)
    p = along_frame + a.T @ multiplier
    return p, frame.transpose_times(k_along_frame + k_a_t @ multiplier)


def metric_of(system, y0, args):
    r"""How a step's `ReducedSystem` finds $M$ (its `metric`): `"position"` where the program of
    $\partial H/\partial p$ computes something from $q$; else a constant, computed once
    per step where it is read from `args`, and otherwise known at trace time:
    `"identity"` or the array (see `nhjax._dependence`)."""
    q, p = y0
    on_position, on_args = velocity_dependence(system, q, p, args)
    if on_position:
        return "position"
    if on_args:
        return system.metric(q, args)
    inverse = evaluated_inverse_metric(system, q, p, args)
    if np.array_equal(inverse, np.eye(q.shape[0])):
        return "identity"
    return jnp.asarray(np.linalg.inv(inverse), dtype=q.dtype)


def metric_is(metric, kind: str) -> bool:
    """Whether `metric` (as `metric_of` gives it) is of the `kind` `"position"` or
    `"identity"`, not an array."""
    return isinstance(metric, str) and metric == kind


class ReducedPoint(NamedTuple):
    r"""What the reduced field needs at one point $\zeta = (q, \rho)$: the frame
    $X(q)$ (not formed), the momentum $p(\zeta)$, $\nabla\mathcal{H}(\zeta)$, and
    products with $J = \partial_q(X^Tp)$ and $J^T$ at fixed $p$
    (`ReducedSystem.at`). From these, `structure_times` gives $\Pi(\zeta)v$ without
    forming $\Pi$ or $J$: with $B = JX - (JX)^T$ (skewMat),

    $$\Pi v = \begin{pmatrix} Xv_\rho \\ -X^Tv_q + Bv_\rho\end{pmatrix}
      = \begin{pmatrix} Xv_\rho \\ J(Xv_\rho) - X^T(v_q + J^Tv_\rho)\end{pmatrix}.$$
    """

    frame: HouseholderFrame
    momentum: Float[Array, " n"]
    gradient: Float[Array, " N"]
    contracted_times: Callable[[Array], Array]
    contracted_transpose_times: Callable[[Array], Array]

    def structure_times(self, v: Float[Array, " N"]) -> Float[Array, " N"]:
        r"""$\Pi(\zeta)v$."""
        n = self.frame.shape[0]
        along_q, along_rho = v[:n], v[n:]
        moved = self.frame.times(along_rho)
        normal = along_q + self.contracted_transpose_times(along_rho)
        return jnp.concatenate([moved, self.contracted_times(moved) - self.frame.transpose_times(normal)])


def split_reduced(zeta, signs):
    """$(q, \\rho)$ from $\\zeta$ of size $n + m = 2n - k$."""
    n = (zeta.shape[0] + signs.shape[0]) // 2
    return zeta[:n], zeta[n:]


class ReducedSystem(eqx.Module):
    r"""The reduced equations (dynamical) of a `NonholonomicSystem` for the Householder
    frame $X(q; s)$, with everything evaluated from $H$ and $A$ alone (§3.3):

    - $\mathcal{H}(q, \rho) = H(q, p)$, $p = p(q, \rho)$ by (ptoptilde);
    - $\partial\mathcal{H}/\partial\rho = y = (X^TMX)^{-1}\rho$ and
      $\partial\mathcal{H}/\partial q^i = \partial_{q^i}H(q, p) - p^T\,\partial_iX\,y$,
      eq. (eq:Htgrad) (the $\partial g$ and $\partial V$ terms are $\partial_q H$ at
      fixed $p$);
    - $\Pi = \begin{pmatrix} 0 & X \\ -X^T & B\end{pmatrix}$ with
      $B_{ab} = p^T(\partial X_a[X_b] - \partial X_b[X_a])$, eqs. (PiMat), (skewMat).

    The frame's derivative enters both only through $J = \partial_q(X^Tp)$ at fixed
    $p$, $J_{ai} = p^T\partial_iX_a$ (`contracted_frame_derivative`): $B = JX - (JX)^T$
    and $p^T\partial_iX\,y = (J^Ty)_i$, and the field $\Pi\nabla\mathcal{H}$ needs only
    the products $Jv$ and $J^Tw$ (`ReducedPoint`). With `"autodiff"` they come from
    one linearisation of $q \mapsto X(q)^Tp$ ($k$ Householder reflections of the
    vector $p$, through the QR), applied forward and transposed; $J$ itself, for
    `structure`, by `jax.jacfwd` of the same map. With `"central_difference"`,
    $J = (X(q + \epsilon e_i) - X(q - \epsilon e_i))^Tp/2\epsilon$,
    the paper's finite-difference remark, with $\epsilon$ = `difference_step`
    (GONZALEZ-R passes $|h|$, as the paper does, so the method stays second order).

    `metric` says how $M(q)$ enters: `"position"` (default) through products with
    $\partial^2H/\partial p^2$ at each $q$ (`momentum_by_projection`); `"identity"` for
    $M = I$; or a constant $(n, n)$ array. A caller who knows the metric is constant
    (GONZALEZ-R decides it from the program of $\partial H/\partial p$,
    `nhjax._dependence`) saves the $k + 1$ products and a $k \times k$ solve at every
    evaluation for an $m \times m$ solve, and for $M = I$ needs no solve.

    **$M = I$ without the frame.** Where $H = \tfrac12|p|^2 + V(q)$, the Householder
    frame is orthonormal, so $\mathcal{H}(q, \rho) = \tfrac12|X\rho|^2 + V =
    \tfrac12|\rho|^2 + H(q, 0)$, and in (eq:Htgrad) the term $p^T\partial_iX\,y =
    \rho^TX^T\partial_iX\rho$ vanishes ($X^T\partial_iX$ is skew, from $X^TX = I$):
    $\nabla\mathcal{H} = (\partial_qH(q, 0), \rho)$. nhjax evaluates $\mathcal{H}$ in
    this form, which needs no QR, and with `"autodiff"` $\nabla\mathcal{H}$ too, which
    is then exactly the gradient of the function evaluated (the Gonzalez correction's
    Taylor form assumes it). With `"central_difference"` the gradient stays (eq:Htgrad)
    with the differenced $\partial X$, whose $X^T\partial_iX$ is skew only to
    $O(\epsilon^2)$: the paper's method as its remark describes it.
    The values differ from $H(q, X\rho)$ by rounding only; the energy a method keeps
    exactly is $\mathcal{H}$, and $H(q', p')$ reported at $p' = X\rho'$ equals it to
    rounding. The frame's derivatives then enter only $\Pi$, so derivative programs
    (of a step's root, `nhjax._solver.base._implicit_root`) carry second derivatives of
    the QR only there.
    """

    system: Any  # a NonholonomicSystem
    signs: Float[Array, " k"]
    derivative: Derivative = eqx.field(default="autodiff", static=True)
    difference_step: Any = None
    metric: Any = "position"

    def __check_init__(self):
        check_derivative(self.derivative)
        if isinstance(self.metric, str) and self.metric not in ("position", "identity"):
            raise ValueError(f'metric must be "position", "identity" or an array, got {self.metric!r}.')
        if self.derivative == "central_difference" and self.difference_step is None:
            raise ValueError('derivative="central_difference" needs a difference_step.')
        check_difference_step(self.derivative, self.difference_step)

    def momentum_in_frame(self, q, frame: HouseholderFrame, rho, args):
        """`momentum_in_frame` with this system's metric at `q`; for a metric that
        depends on $q$, `momentum_by_projection`."""
        if metric_is(self.metric, "identity"):
            return momentum_in_frame(frame, rho)
        if metric_is(self.metric, "position"):
            return momentum_by_projection(self.system, q, frame, rho, args)
        return momentum_in_frame(frame, rho, self.metric)

    def frame(self, q, args) -> HouseholderFrame:
        """The frame $X(q; s)$ with this system's signs, not formed."""
        return self.system.frame_operator(q, args, self.signs)

    def to_reduced(self, y, args, frame: HouseholderFrame | None = None) -> Float[Array, " n+m"]:
        r"""$\zeta = (q, \rho)$ with $\rho = X^T p$, eq. (ptildetop). `frame`: $X(q)$
        where the caller has it (`None`: factorised here)."""
        q, p = y
        frame = self.frame(q, args) if frame is None else frame
        return jnp.concatenate([q, frame.transpose_times(p)])

    def from_reduced(self, zeta, args, frame: HouseholderFrame | None = None) -> tuple[Array, Array]:
        r"""$(q, p)$ from $\zeta = (q, \rho)$, eq. (ptoptilde); `frame` as for
        `to_reduced`."""
        q, rho = split_reduced(zeta, self.signs)
        frame = self.frame(q, args) if frame is None else frame
        return q, self.momentum_in_frame(q, frame, rho, args)[0]

    def hamiltonian(self, zeta, args) -> Float[Array, ""]:
        if metric_is(self.metric, "identity"):
            q, rho = split_reduced(zeta, self.signs)
            return self.system.hamiltonian(q, jnp.zeros_like(q), args) + 0.5 * rho @ rho
        q, p = self.from_reduced(zeta, args)
        return self.system.hamiltonian(q, p, args)

    def start_of_step(self, zeta, args, frame: HouseholderFrame | None = None):
        r"""What `energy_segment` needs of a step's start $\zeta$:
        $\mathcal{H}(\zeta)$, and the canonical momentum $p(\zeta)$ (`None` for
        $M = I$, whose $\mathcal{H}$ needs none); `frame` as for `to_reduced`."""
        if metric_is(self.metric, "identity"):
            return self.hamiltonian(zeta, args), None
        q, p = self.from_reduced(zeta, args, frame)
        return self.system.hamiltonian(q, p, args), p

    def energy_segment(self, zeta, momentum, zeta1, args):
        r"""$\mathcal{H}(\zeta')$, and a segment with a gradient along it whose integral
        is $\mathcal{H}(\zeta') - \mathcal{H}(\zeta)$, for that difference without the
        cancellation of the two values (`nhjax._discrete_gradient.segment_difference`):
        `(value, (gradient, start, end))`, `gradient(z, args)` a callable pytree. The
        gradients need no frame derivative: for $M = I$ the segment is in $\zeta$,
        $\nabla\mathcal{H} = (\partial_qH(q, 0), \rho)$; otherwise it runs from
        $(q, p)$ to $(q', p')$ in canonical coordinates, $p$ = `momentum` and
        $p' = p(\zeta')$, with $\nabla H$ of the user's $H$ ($\mathcal{H}(\zeta) =
        H(q, p(\zeta))$, so the two differences are one; the frame at $q'$ that $p'$
        needs is the one $\mathcal{H}(\zeta')$ needs anyway)."""
        if metric_is(self.metric, "identity"):
            return self.hamiltonian(zeta1, args), (self.reduced_gradient, zeta, zeta1)
        q, _ = split_reduced(zeta, self.signs)
        q1, p1 = self.from_reduced(zeta1, args)
        start, end = jnp.concatenate([q, momentum]), jnp.concatenate([q1, p1])
        return self.system.hamiltonian(q1, p1, args), (self.canonical_gradient, start, end)

    def reduced_gradient(self, zeta, args) -> Float[Array, " N"]:
        r"""$\nabla\mathcal{H}(\zeta)$ by autodiff of `hamiltonian` (for $M = I$ it needs
        no frame)."""
        return jax.grad(self.hamiltonian)(zeta, args)

    def canonical_gradient(self, z, args) -> Float[Array, " 2n"]:
        r"""$\nabla H(q, p)$ of the user's $H$ at $z = (q, p)$."""
        n = z.shape[0] // 2
        return jnp.concatenate(jax.grad(self.system.hamiltonian, argnums=(0, 1))(z[:n], z[n:], args))

    def position_gradient(self, q, p, args) -> Float[Array, " n"]:
        r"""$\partial_qH(q, p)$ at fixed $p$, the first term of (eq:Htgrad); for $M = I$
        $\partial_qH(q, 0)$, the whole $\partial_q\mathcal{H}$ (see the class
        docstring), which needs no momentum."""
        if metric_is(self.metric, "identity"):
            return jax.grad(self.system.hamiltonian)(q, jnp.zeros_like(q), args)
        return jax.grad(self.system.hamiltonian)(q, p, args)

    def contracted_frame_derivative(self, q, p, args) -> Float[Array, "m n"]:
        r"""$J = \partial_q(X(q)^Tp)$ at fixed $p$, formed: $J_{ai} = \sum_j p_j\,\partial_iX_{ja}$
        ($n$ tangents, or $2n$ evaluations for `"central_difference"`)."""
        transpose_times = lambda x: self.frame(x, args).transpose_times(p)  # noqa: E731
        if self.derivative == "autodiff":
            return jax.jacfwd(transpose_times)(q)
        step = jnp.asarray(self.difference_step, q.dtype)
        offsets = step * jnp.eye(q.shape[0], dtype=q.dtype)
        differences = jax.vmap(lambda e: (transpose_times(q + e) - transpose_times(q - e)) / (2 * step))(offsets)
        return differences.T

    def formed_frame_derivative(self, zeta, args) -> Float[Array, "m n"]:
        r"""$J = \partial_q(X^Tp)$ at $\zeta$, $p = p(\zeta)$, formed
        (`contracted_frame_derivative`)."""
        q, rho = split_reduced(zeta, self.signs)
        return self.contracted_frame_derivative(q, self.momentum_in_frame(q, self.frame(q, args), rho, args)[0], args)

    def at(self, zeta, args, contracted: Float[Array, "m n"] | None = None) -> ReducedPoint:
        r"""The `ReducedPoint` at $\zeta$: $\nabla\mathcal{H}$ by (eq:Htgrad),
        $\partial_{q^i}\mathcal{H} = \partial_{q^i}H(q, p) - (J^Ty)_i$, and products
        with $J = \partial_q(X^Tp)$ (`contracted_frame_derivative`) and its transpose.

        With `"autodiff"` the products are matrix-free: one linearisation of
        $q \mapsto X(q)^Tp$ ($k$ reflections of one vector, through the QR), applied
        forward ($Jv$) and transposed ($J^Tw$), so that a field evaluation costs a few
        passes through the QR instead of $n$ tangents of it, which made GONZALEZ-R's
        cost grow like $n^4$ (`benchmarks/scaling.py`). The factorisation at $q$ is
        linearised once, and its reflectors are the frame: $Jv$ is the derivative of
        $X^Tp$ in the reflectors along theirs along $v$. Linearising
        $q \mapsto X(q)^Tp$ whole factorised $A(q)^T$ a second time beside the frame's
        own factorisation, which XLA did not merge. With `"central_difference"`
        $J$ is formed by differences, the paper's remark. `contracted`: a given $J$,
        that of another point (`nhjax.GonzalezR.chord_jacobian`), in place of this
        point's."""
        q, rho = split_reduced(zeta, self.signs)
        linearised = contracted is None and self.derivative == "autodiff"
        if linearised:
            frame, contracted_products = self.linearised_frame(q, args)
        else:
            frame = self.frame(q, args)
        p, y = self.momentum_in_frame(q, frame, rho, args)
        if linearised:
            times, transpose_times = contracted_products(p)
        else:
            if contracted is None:
                contracted = self.contracted_frame_derivative(q, p, args)
            times = lambda v: product(contracted, v)  # noqa: E731
            transpose_times = lambda w: product(w, contracted)  # noqa: E731
        grad_q = self.position_gradient(q, p, args)
        if not (metric_is(self.metric, "identity") and self.derivative == "autodiff"):
            grad_q = grad_q - transpose_times(y)
        return ReducedPoint(frame, p, jnp.concatenate([grad_q, y]), times, transpose_times)

    def linearised_frame(self, q, args) -> tuple[HouseholderFrame, Callable]:
        r"""$X(q)$ from one linearised factorisation of $A(q)^T$, and a function that
        gives, for a momentum $p$, the products with $J = \partial_q(X^Tp)$ at fixed
        $p$ and with $J^T$ (`at`): $Jv$ is the derivative of $X^Tp$ in the reflectors
        along the reflectors' own derivative along $v$, and $J^Tw$ its transpose."""
        vectors, vectors_along = jax.linearize(lambda x: self.frame(x, args).vectors, q)

        def contracted_products(p):
            _, product_along = jax.linearize(lambda w: HouseholderFrame(w).transpose_times(p), vectors)
            times = lambda v: product_along(vectors_along(v))  # noqa: E731
            transpose = jax.linear_transpose(times, q)
            return times, lambda w: transpose(w)[0]

        return HouseholderFrame(vectors), contracted_products

    def field_jacobian(self, zeta, t, args, frame_turn: bool = False) -> Float[Array, "N N"]:
        r"""An approximation of the derivative of the field $\Pi\nabla\mathcal{H}$ (plus
        the applied force in the frame, at time `t`) at $\zeta$, with the frame held to
        first order, for chord matrices (`nhjax.GonzalezR.chord_jacobian`):

        - the momentum, the velocity $y$ and $\partial_qH$ vary exactly, by
          `jax.jacfwd` with the frame formed once at $q$
          (`nhjax._householder.FormedFrame`): with $M = I$ this is
          $\begin{pmatrix} 0 & X \\ -X^T\partial_q^2V & 0\end{pmatrix}$;
        - the frame moves out of $\mathcal{D}$ as $\ker A$ does:
          $X(q + \delta) \approx X - A^+\,\partial A[\delta]\,X$, $A^+ =
          A^T(AA^T)^{-1}$, which keeps $A X = 0$ to first order and needs derivatives of
          $A$ only ($A(q)v$ and $A(q)^T\lambda$ along $n$ tangents), not of the QR;
        - left out: the frame's rotation within $\mathcal{D}$ ($X^T\partial X$, which
          the Householder construction fixes), the block $B$ and the term
          $J^Ty$ of (eq:Htgrad), all derivatives of the QR.

        Those would take $n$ tangents (or $n$ shifted factorisations) through the
        QR, $O(n^2k^2)$ work: GONZALEZ-R's cost grew like $n^4$ with them
        (`benchmarks/scaling.py`).

        `frame_turn`: also the derivative of the $\rho$-rows' $J(p)Xy$ in $p$, which
        for $J(p)_{ai} = p^T\partial_iX_a$ linear in $p$ is $(\partial_uX)^T$ with
        $u = Xy$: the frame's turn along the velocity, one tangent through the QR.
        Of the terms left out it is the one that sets the chord iteration's
        contraction where the frame turns within $\mathcal{D}$. Measured by adding
        left-out terms to the matrix (GONZALEZ-R on the synthetic systems of
        `benchmarks/scaling.py`, $h = 0.05$, iterations per step): the derivative of
        $B$ in $y$ changes them by under 0.2; this term takes them from 8.4 to 5.7
        at $n = 8$, 9.0 to 5.9 at $n = 16$ and 9.9 to 7.1 at $n = 64$; the rest, to
        the exact matrix's 3.9 and 4.0 at $n = 8, 16$, is $J$'s derivative in $q$
        (second derivatives of the QR). On the gearbox, whose frame turns only out
        of $\mathcal{D}$, it changes nothing, nor on Euler's disk, whose iterations
        (9.0 at $h = 0.05$, 4.6 with the exact matrix) come from $J$'s derivative
        in $q$; on the energy-preserving collocation it did not pay for its
        tangent. So it is the caller's choice."""
        system = self.system
        q, rho = split_reduced(zeta, self.signs)
        turn = None
        if frame_turn:
            # The frame and its derivative from one linearised factorisation.
            matrix, matrix_along = jax.linearize(lambda x: self.frame(x, args).matrix(), q)
            frame = FormedFrame(matrix)
            turn = matrix_along(frame.times(self.momentum_in_frame(q, frame, rho, args)[1]))
        else:
            frame = FormedFrame(self.frame(q, args).matrix())

        def field_in_fixed_frame(z):
            x, rho = split_reduced(z, self.signs)
            p, y = self.momentum_in_frame(x, frame, rho, args)
            force = self.position_gradient(x, p, args)
            along_rho = -frame.transpose_times(force)
            if turn is not None:
                # Its value is not used: only its derivative in p, with the turn held.
                along_rho = along_rho + turn.T @ p
            field = jnp.concatenate([frame.times(y), along_rho])
            if system.is_forced():
                applied = system.applied_force(t, x, p, args, frame.times(y))
                field = field.at[q.shape[0] :].add(frame.transpose_times(applied))
            return field, (y, force)

        jacobian, (y, force) = jax.jacfwd(field_in_fixed_frame, has_aux=True)(zeta)
        a = system.constraints(q, args)
        gram = a @ a.T
        velocity = frame.times(y)
        multiplier = solve_spd(gram, a @ force)
        along_velocity, along_multiplier = jax.jacfwd(
            lambda x: (system.constraints(x, args) @ velocity, system.constraints(x, args).T @ multiplier)
        )(q)
        frame_motion = jnp.concatenate(
            [-a.T @ solve_spd(gram, along_velocity), frame.transpose_times(along_multiplier)]
        )
        # Where A has lost rank, A^+ is undefined and the step fails on the rank check
        # at its end (`NonholonomicSystem.step_result`): the matrix goes without the
        # term rather than turn the iteration's arithmetic to NaN first.
        frame_motion = jnp.where(jnp.isfinite(frame_motion), frame_motion, 0.0)
        return jacobian.at[:, : q.shape[0]].add(frame_motion)

    def structure_and_gradient(self, zeta, args) -> tuple[Float[Array, "N N"], Float[Array, " N"]]:
        r"""$\Pi(\zeta)$, formed from $X$ and $B = JX - (JX)^T$ (PiMat), (skewMat), and
        $\nabla\mathcal{H}(\zeta)$."""
        q, _ = split_reduced(zeta, self.signs)
        contracted = self.formed_frame_derivative(zeta, args)
        frame = self.frame(q, args).matrix()
        along_frame = contracted @ frame
        # The gradient from the same J, not from a second, linearised one.
        return adapted_structure(frame, along_frame - along_frame.T), self.at(zeta, args, contracted).gradient

    def structure(self, zeta, args) -> Float[Array, "N N"]:
        return self.structure_and_gradient(zeta, args)[0]

    def dissipation(self, zeta, args) -> Float[Array, "N N"]:
        r"""The system's dissipation in the frame, $R_\zeta = \begin{pmatrix} 0 & 0 \\
        0 & X^TDX\end{pmatrix}$ at $(q, p(\zeta))$: with $v = Xy$,
        $y = \partial\mathcal{H}/\partial\rho$, the $\rho$-rows of
        $R_\zeta\nabla\mathcal{H}$ are $X^TDv$, what the damping force $-Dv$ adds to
        $\dot\rho = \tfrac{d}{dt}(X^Tp)$ (the constraint force drops out,
        $X^TA^T = 0$)."""
        q, p = self.from_reduced(zeta, args)
        frame = self.frame(q, args).matrix()
        block = frame.T @ self.system.dissipation(q, p, args) @ frame
        n, m = q.shape[0], frame.shape[1]
        return jnp.zeros((n + m, n + m), block.dtype).at[n:, n:].set(block)

    def force(self, t, zeta, args) -> Float[Array, " N"]:
        r"""The system's force in the frame, $g_\zeta = (0, X^TF(t, q, p(\zeta)))$."""
        q, p = self.from_reduced(zeta, args)
        along_frame = self.frame(q, args).transpose_times(self.system.force(t, q, p, args))
        return jnp.concatenate([jnp.zeros_like(q), along_frame])

    def with_applied_force(
        self, t, zeta, point: ReducedPoint, gradient: Float[Array, " N"], field: Float[Array, " N"], args
    ) -> tuple[Float[Array, " N"], tuple[Array, Array] | None]:
        r"""`field` plus $(0, X^T(F - Dv))$ with $v = X\,\text{gradient}_\rho$, the
        velocity of the gradient's $\rho$-part, and $X$, $p$, $D$, $F$ at `point`
        ($\zeta$) and time `t`: the force and the damping act on the $\rho$-rows only,
        so the $q$-update stays in $\mathcal{D}$ and the constraint holds as without
        them. Also their power along $v$, (supplied, dissipated)
        (`NonholonomicSystem.power_along`); `field` and `None` for a conservative
        system."""
        if not self.system.is_forced():
            return field, None
        q, _ = split_reduced(zeta, self.signs)
        n = q.shape[0]
        velocity = point.frame.times(gradient[n:])
        applied = self.system.applied_force(t, q, point.momentum, args, velocity)
        field = field.at[n:].add(point.frame.transpose_times(applied))
        return field, self.system.power_along(t, q, point.momentum, velocity, args)

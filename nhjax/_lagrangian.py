r"""Mechanical systems given by their Lagrangian: the Hamiltonian by the Legendre
transform, through autodiff.

For $L(q, \dot q) = \tfrac12\dot q^TM(q)\dot q - V(q)$ (mechanical type) the Legendre
transform $p = \partial L/\partial\dot q = M(q)\dot q$,
$H(q, p) = p^T\dot q - L(q, \dot q)$ gives
$$H(q, p) = \tfrac12 p^TM(q)^{-1}p + V(q),\qquad
  M(q) = \frac{\partial^2L}{\partial\dot q^2}(q, 0),\quad V(q) = -L(q, 0),$$
exactly when $L$ is of mechanical type; for any other $L$ these formulas describe a
different system, so `mechanical_defect` checks the type at the initial state
(`nhjax.NonholonomicSystem.initial_state_result`).
"""

from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._linalg import is_quadratic_form, jacobian_by_columns, solve_spd
from ._user_function import traced_once


Lagrangian = Callable[[Float[Array, " n"], Float[Array, " n"], Any], Float[Array, ""]]


class LegendreHamiltonian(eqx.Module):
    r"""$H(q, p) = \tfrac12p^TM(q)^{-1}p + V(q)$ with $M = \partial^2L/\partial\dot q^2$ at
    $\dot q = 0$ and $V = -L(q, 0)$: the Legendre transform of `lagrangian` (module
    docstring), a function `(q, p, args) -> scalar` like any Hamiltonian, whose
    derivatives are first derivatives of $L$ at the velocity $M^{-1}p$
    (`_legendre_transform_jvp`), not autodiff through $M$ and the solve."""

    owns_tracing: ClassVar[bool] = True
    lagrangian: Lagrangian = eqx.field(converter=traced_once)

    def mass_matrix(self, q: Float[Array, " n"], args: Any) -> Float[Array, "n n"]:
        r"""$M(q)$, column by column: $Me_i$ is the derivative of
        $\partial L/\partial\dot q(q, \cdot)$ at $\dot q = 0$ along $e_i$, exact for $L$
        of mechanical type (the only kind this Hamiltonian describes, checked by
        `is_mechanical`), for which $\partial L/\partial\dot q(q, u) = M(q)u$.

        One reverse pass of $L$, linearised once at $\dot q = 0$ and applied to the unit
        velocities one at a time in a loop (`nhjax._linalg.jacobian_by_columns`).
        Batched over the units instead (`jax.vmap`), the products inside $L$ (its
        $M(q)\dot q$) become matrix products, library calls of their own on XLA:CPU,
        on arrays too large for a step's operations to run in sequence; the matrix
        is formed wherever $H$ or a derivative of it is evaluated, several times a step,
        and so Euler's disk from its Lagrangian stepped markedly slower than from its
        mass matrix, where by columns it steps about as fast (`benchmarks/scaling.py`
        times the two forms in turns). Unrolled, the loop's n copies of the pass grew
        the program and its compilation by a third."""
        velocity_gradient = jax.grad(self.lagrangian, argnums=1)
        return jacobian_by_columns(lambda u: velocity_gradient(q, u, args), jnp.zeros_like(q))

    def __call__(self, q: Float[Array, " n"], p: Float[Array, " n"], args: Any) -> Float[Array, ""]:
        return eqx.filter_jit(_legendre_transform)(self, q, p, args)

    def velocity_and_value(self, q, p, args) -> tuple[Float[Array, " n"], Float[Array, ""]]:
        r"""$\dot q = M(q)^{-1}p$ (`_legendre_velocity`) and $H(q, p)$."""
        velocity = _legendre_velocity(self, q, p, args)
        return velocity, 0.5 * p @ velocity - self.lagrangian(q, jnp.zeros_like(q), args)

    def index_one_terms(
        self, q: Float[Array, " n"], p: Float[Array, " n"], rows: Float[Array, "k n"], args: Any
    ) -> tuple[Float[Array, " n"], Float[Array, "n k"], Float[Array, " n"], Float[Array, " k"]]:
        r"""What the index-1 field of a constrained system (`nhjax.NonholonomicSystem.
        multiplier`) needs of $H$ at $(q, p)$, from $M(q)$ formed once: the velocity
        $v = M^{-1}p$, $M^{-1}R^T$ for the constraint's `rows` $R$,
        $\partial_qH = -\partial_qL(q, v)$ (the envelope theorem, as in
        `_legendre_transform_jvp`), and $R\,\partial_qv[v]$, the rows times the
        velocity's derivative along itself at fixed $p$.

        Differentiating $M(q)v = p$ at fixed $p$ gives
        $\partial M[v]\,v + M\,\partial_qv[v] = 0$, and $\partial M[v]\,v =
        \partial_q(\partial L/\partial\dot q)(q, v)[v]$ since
        $\partial L/\partial\dot q(q, u) = M(q)u$: so
        $R\,\partial_qv[v] = -(M^{-1}R^T)^T\partial_q(\partial L/\partial\dot q)
        (q, v)[v]$, one forward-over-reverse pass of $L$, where autodiff of
        $\partial_pH$ in $q$ would differentiate the formation of $M$ and the solve.
        Each evaluation of $H$ or of a derivative of it forms $M$ anew (a loop, which
        XLA does not merge with another), and the field needs four of them, so the
        system takes these together (`benchmarks/scaling.py` times both forms of
        Euler's disk)."""
        mass = self.mass_matrix(q, args)
        solved = solve_spd(mass, jnp.concatenate([p[:, None], rows.T], axis=1))
        velocity, k_rows = solved[:, 0], solved[:, 1:]
        position_gradient = -jax.grad(self.lagrangian, argnums=0)(q, velocity, args)
        momentum_turn = jax.jvp(
            lambda x: jax.grad(self.lagrangian, argnums=1)(x, velocity, args), (q,), (velocity,)
        )[1]
        return velocity, k_rows, position_gradient, -k_rows.T @ momentum_turn

    def at_position(self, q: Float[Array, " n"], args: Any) -> "LegendreAtPosition":
        r"""$p \mapsto H(q, p)$ at this one $q$, with $M(q)^{-1}$ formed once
        (`LegendreAtPosition`)."""
        mass = self.mass_matrix(q, args)
        return LegendreAtPosition(self, q, args, mass, solve_spd(mass, jnp.eye(q.shape[0], dtype=mass.dtype)))

    def is_mechanical(
        self, q: Float[Array, " n"], velocity: Float[Array, " n"], args: Any, tolerance: Callable
    ) -> Bool[Array, ""]:
        r"""Whether $L$ is of mechanical type at `q`, probed along `velocity`:
        $L(q, u) = L(q, 0) + \tfrac12u^TMu$, $\partial L/\partial\dot q(q, 0) = 0$, $M$
        symmetric positive definite (`nhjax._linalg.is_quadratic_form`)."""
        return is_quadratic_form(
            lambda u: self.lagrangian(q, u, args), self.mass_matrix(q, args), velocity, tolerance
        )


class LegendreAtPosition(eqx.Module):
    r"""$H$ at one position $q$, for a method that evaluates it there at several momenta
    or velocities (SI-DLA's kick at $q_{1/2}$, I-DLA's discrete Lagrangian at the
    midpoint): $M(q)$ and $K = M(q)^{-1}$ formed once, $v = Kp$, $p = Mv$, and
    $\partial_qH(q, p) = -\partial_qL(q, Kp)$ (the envelope theorem,
    `_legendre_transform_jvp`), one reverse pass of $L$ where each evaluation of
    $\partial_qH$ would form $M(q)$ again."""

    hamiltonian: LegendreHamiltonian
    q: Float[Array, " n"]
    args: Any
    mass: Float[Array, "n n"]
    inverse_mass: Float[Array, "n n"]

    def inverse_metric(self) -> Float[Array, "n n"]:
        return self.inverse_mass

    def velocity(self, p: Float[Array, " n"]) -> Float[Array, " n"]:
        return self.inverse_mass @ p

    def momentum(self, v: Float[Array, " n"], inverse_metric: Float[Array, "n n"] | None = None) -> Float[Array, " n"]:
        """$M v$ (`inverse_metric` is not needed: $M$ is kept)."""
        del inverse_metric
        return self.mass @ v

    def position_gradient(self, p: Float[Array, " n"]) -> Float[Array, " n"]:
        return -jax.grad(self.hamiltonian.lagrangian, argnums=0)(self.q, self.velocity(p), self.args)


@eqx.filter_custom_jvp
def _legendre_transform(hamiltonian: LegendreHamiltonian, q, p, args):
    return hamiltonian.velocity_and_value(q, p, args)[1]


@_legendre_transform.def_jvp
def _legendre_transform_jvp(primals, tangents):
    r"""$dH = \dot q^T dp - \partial_qL(q, \dot q)\,dq - \partial_{\text{args}}L(q, \dot q)
    \,d\text{args}$ at $\dot q = M^{-1}p$: $H(q, p) = \max_{\dot q}\,(p^T\dot q - L(q,
    \dot q))$ for $L$ convex in $\dot q$, and the maximiser's own variation drops out
    (the envelope theorem; for mechanical $L$, $-\partial_qL(q, \dot q) =
    -\tfrac12\dot q^T\partial_qM\,\dot q + \partial_qV = \partial_qH$ exactly). So the
    derivatives of $H$ are first derivatives of $L$ at the velocity, not derivatives of
    $M = \partial^2L/\partial\dot q^2$ and of the solve by it: derivatives of $H$ of
    any order trace $L$ to one order less."""
    hamiltonian, q, p, args = primals
    _, q_dot, p_dot, args_dot = tangents
    velocity, value = hamiltonian.velocity_and_value(q, p, args)
    q_dot, args_dot = _position_and_parameter_tangents(q, q_dot, args, args_dot)
    _, lagrangian_dot = eqx.filter_jvp(
        lambda q_, args_: hamiltonian.lagrangian(q_, velocity, args_), (q, args), (q_dot, args_dot)
    )
    # None where L depends on neither q nor a differentiable parameter (a free body's
    # kinetic energy with its masses as numbers): that part of dH is zero.
    value_dot = jnp.zeros_like(value) if lagrangian_dot is None else -lagrangian_dot
    if p_dot is not None:
        value_dot = value_dot + velocity @ p_dot
    return value, value_dot


def _position_and_parameter_tangents(q, q_dot, args, args_dot):
    """The tangents of `q` and of `args` in a custom JVP, zeros where none is given
    (`None`: not differentiated), so that one `jax.jvp` of $L$ serves."""
    q_dot = jnp.zeros_like(q) if q_dot is None else q_dot
    if args_dot is None:  # no parameter differentiated
        args_dot = jax.tree.map(lambda _: None, args)
    args_dot = jax.tree.map(
        lambda leaf, t: t if t is not None else (jnp.zeros_like(leaf) if eqx.is_inexact_array(leaf) else None),
        args, args_dot, is_leaf=lambda t: t is None,
    )
    return q_dot, args_dot


@eqx.filter_custom_jvp
def _legendre_velocity(hamiltonian: LegendreHamiltonian, q, p, args):
    return solve_spd(hamiltonian.mass_matrix(q, args), p)


@_legendre_velocity.def_jvp
def _legendre_velocity_jvp(primals, tangents):
    r"""$d\dot q = M^{-1}\big(dp - \partial_{(q,\text{args})}(\partial L/\partial\dot q)
    (q, \dot q)[dq, d\text{args}]\big)$ at $\dot q = M(q)^{-1}p$: the differential of
    $p = \partial L/\partial\dot q(q, \dot q)$, whose derivative in $\dot q$ is $M(q)$
    for $L$ of mechanical type. One forward-over-reverse pass of $L$ and a solve with
    the $M$ already formed, where autodiff of the solve would differentiate the
    formation of $M$ (its $n$ columns, each a second derivative of $L$), which every
    second derivative of $H$ (a chord matrix) would otherwise do."""
    hamiltonian, q, p, args = primals
    _, q_dot, p_dot, args_dot = tangents
    mass = hamiltonian.mass_matrix(q, args)
    velocity = solve_spd(mass, p)
    if q_dot is None and all(t is None for t in jax.tree.leaves(args_dot, is_leaf=lambda t: t is None)):
        # Only p varies (K = dv/dp): no pass of L.
        momentum_dot = None
    else:
        q_dot, args_dot = _position_and_parameter_tangents(q, q_dot, args, args_dot)
        momentum_of = jax.grad(hamiltonian.lagrangian, argnums=1)
        _, momentum_dot = eqx.filter_jvp(
            lambda q_, args_: momentum_of(q_, velocity, args_), (q, args), (q_dot, args_dot)
        )
    # None also where the momentum depends on neither q nor a differentiable parameter
    # (a constant metric with its masses as numbers).
    momentum_dot = jnp.zeros_like(p) if momentum_dot is None else momentum_dot
    rhs = -momentum_dot if p_dot is None else p_dot - momentum_dot
    return velocity, solve_spd(mass, rhs)

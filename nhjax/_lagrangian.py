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
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._linalg import is_quadratic_form, solve_spd


Lagrangian = Callable[[Float[Array, " n"], Float[Array, " n"], Any], Float[Array, ""]]


class LegendreHamiltonian(eqx.Module):
    r"""$H(q, p) = \tfrac12p^TM(q)^{-1}p + V(q)$ with $M = \partial^2L/\partial\dot q^2$ at
    $\dot q = 0$ and $V = -L(q, 0)$: the Legendre transform of `lagrangian` (module
    docstring), a function `(q, p, args) -> scalar` like any Hamiltonian."""

    lagrangian: Lagrangian

    def mass_matrix(self, q: Float[Array, " n"], args: Any) -> Float[Array, "n n"]:
        return jax.hessian(self.lagrangian, argnums=1)(q, jnp.zeros_like(q), args)

    def __call__(self, q: Float[Array, " n"], p: Float[Array, " n"], args: Any) -> Float[Array, ""]:
        potential = -self.lagrangian(q, jnp.zeros_like(q), args)
        return 0.5 * p @ solve_spd(self.mass_matrix(q, args), p) + potential

    def is_mechanical(
        self, q: Float[Array, " n"], velocity: Float[Array, " n"], args: Any, tolerance: Callable
    ) -> Bool[Array, ""]:
        r"""Whether $L$ is of mechanical type at `q`, probed along `velocity`:
        $L(q, u) = L(q, 0) + \tfrac12u^TMu$, $\partial L/\partial\dot q(q, 0) = 0$, $M$
        symmetric positive definite (`nhjax._linalg.is_quadratic_form`)."""
        return is_quadratic_form(
            lambda u: self.lagrangian(q, u, args), self.mass_matrix(q, args), velocity, tolerance
        )

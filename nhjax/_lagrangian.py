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

from ._linalg import solve_spd


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
        r"""Whether $L$ is of mechanical type at `q`, along `velocity` and two fixed
        directions: $L(q, u) = L(q, 0) + \tfrac12u^TMu$, $\partial L/\partial\dot q(q, 0)
        = 0$, $M$ symmetric positive definite; `tolerance(dtype, scale)` is the
        allowed rounding."""
        n = q.shape[0]
        mass = self.mass_matrix(q, args)
        base = self.lagrangian(q, jnp.zeros_like(q), args)
        probes = jnp.stack([velocity, jnp.ones_like(q), jnp.cos(jnp.arange(n, dtype=q.dtype))])

        def quadratic_along(u):
            kinetic = 0.5 * u @ mass @ u
            value = self.lagrangian(q, u, args)
            return jnp.abs(value - base - kinetic) <= tolerance(
                q.dtype, jnp.abs(value) + jnp.abs(base) + jnp.abs(kinetic)
            )

        quadratic = jnp.all(jax.vmap(quadratic_along)(probes))
        linear_term = jax.grad(self.lagrangian, argnums=1)(q, jnp.zeros_like(q), args)
        scale = jnp.max(jnp.abs(mass))
        no_linear = jnp.max(jnp.abs(linear_term)) <= tolerance(q.dtype, scale)
        symmetric = jnp.max(jnp.abs(mass - mass.T)) <= tolerance(q.dtype, scale)
        positive = jnp.all(jnp.isfinite(jnp.linalg.cholesky(mass)))
        return quadratic & no_linear & symmetric & positive

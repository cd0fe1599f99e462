r"""GONZALEZ-F, eq. (simpDirect): the Gonzalez discrete gradient on $T^*Q$ with
constraint forces."""

from typing import ClassVar

import jax.numpy as jnp
import optimistix as optx

from .._discrete_gradient import gonzalez
from .._nonholonomic import NonholonomicSystem
from .base import AbstractMethod, increment_scale
from .chord import midpoint_gradient


class GonzalezF(AbstractMethod):
    r"""GONZALEZ-F, the direct method (simpDirect) on $z = (q, p)$:

    $$\frac{z' - z}{h} = J\,\bar\nabla_2 H(z, z') + \begin{pmatrix} 0 \\ A(\bar q)^T\lambda
      \end{pmatrix},\qquad A(\bar q)\,\bar\nabla_2 H(z, z')_p = 0,$$

    with $\bar q = (q + q')/2$, the Gonzalez discrete gradient `nhjax.gonzalez` of $H$ on
    $\mathbb{R}^{2n}$, and $2n + k$ unknowns $(q', p', \lambda)$. The second equation
    makes the constraint force do no discrete work, so $H(z') = H(z)$ to roundoff; but
    it constrains the discrete-gradient velocity at $\bar q$, not $\partial_pH$ at the
    step's end, so $A(q)\partial_pH(q, p) = 0$ holds only to the method's accuracy.
    Second order and time-symmetric.

    Each step solves for the scaled increment $(z' - z)/s$, $s = 1 + |z|$ (elementwise),
    and the impulse $h\lambda$, from the explicit Euler predictor of the index-1
    equations.

    **Arguments:** `root_finder`, `root_find_max_steps` as for `nhjax.DiscreteGradient`.
    """

    term_structure: ClassVar = NonholonomicSystem

    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 20

    def order(self, terms):
        del terms
        return 2

    @staticmethod
    def _residual(unknowns, data, discrete_gradient=gonzalez):
        system, z, h, scale, args = data
        (n2,) = z.shape
        n = n2 // 2
        u, impulse = unknowns[:n2], unknowns[n2:]
        z1 = z + scale * u
        hamiltonian = lambda x, args: system.hamiltonian(x[:n], x[n:], args)  # noqa: E731
        gradient = discrete_gradient(hamiltonian, z, z1, args)
        a = system.constraints(0.5 * (z[:n] + z1[:n]), args)
        flow = jnp.concatenate([gradient[n:], -gradient[:n]])
        force = jnp.concatenate([jnp.zeros((n,), z.dtype), a.T @ impulse])
        velocity_scale = jnp.max(scale[:n])
        return jnp.concatenate(
            [u - (h * flow + force) / scale, (h / velocity_scale) * (a @ gradient[n:])]
        )

    @classmethod
    def _midpoint_residual(cls, unknowns, data):
        """The residual with the midpoint gradient in place of the discrete gradient
        (for the Jacobian approximation, see `nhjax._solver.chord`)."""
        return cls._residual(unknowns, data, midpoint_gradient)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        system, h = self.system_and_step(terms, t0, t1)
        q, p = y0
        n = q.shape[0]
        z = jnp.concatenate([q, p])
        scale = increment_scale(z)
        velocity, acceleration = system.vf(t0, y0, args)
        guess = jnp.concatenate(
            [h * jnp.concatenate([velocity, acceleration]) / scale, h * system.multiplier(y0, args)]
        )
        data = (system, z, h, scale, args)
        unknowns, result, steps = self.solve(self._residual, guess, data, self._midpoint_residual)
        z1 = z + scale * unknowns[: 2 * n]
        return self.finish(y0, (z1[:n], z1[n:]), result, steps, solver_state)

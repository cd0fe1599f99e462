r"""The continuous gearbox driven by an asymmetric pendulum of §4.4 (after Modin &
Verdier 2014).

$Q = \mathbb{R}^3$, $M = I$, $H = \tfrac12|p|^2 + V(q)$,
$V = \tfrac12(q_1^2 + q_2^2) + \cos q_3 - \tfrac15\sin 2q_3$, one constraint
$\dot q_1 + \sin(q_3)\dot q_2 = p_1 + \sin(q_3)p_2 = 0$.

**The sign of V.** The paper prints $H = \tfrac12|p|^2 - V$. That makes both
oscillators unstable and contradicts its own description ("harmonic oscillators coupled
through nonholonomic constraints"), so nhjax uses $H = \tfrac12|p|^2 + V$.

Because $A$ has no $q_3$ column and $V$ separates, the pendulum energy
$H_3 = \tfrac12p_3^2 + \cos q_3 - \tfrac15\sin 2q_3$ and $H - H_3$ are conserved by the
exact flow separately (`pendulum_energy`); a discrete-gradient method keeps only their
sum exactly.
"""

from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._nonholonomic import NonholonomicSystem
from ._example import AbstractExample


def potential(q, args=None) -> Float[Array, ""]:
    del args
    return 0.5 * (q[0] ** 2 + q[1] ** 2) + jnp.cos(q[2]) - 0.2 * jnp.sin(2 * q[2])


def _hamiltonian(q, p, args):
    return 0.5 * p @ p + potential(q, args)


def _lagrangian(q, qdot, args):
    return 0.5 * qdot @ qdot - potential(q, args)


def _constraints(q, args):
    del args
    one = jnp.ones_like(q[2])
    return jnp.stack([one, jnp.sin(q[2]), jnp.zeros_like(one)])[None, :]


def pendulum_energy(q, p) -> Float[Array, "..."]:
    r"""$H_3 = \tfrac12p_3^2 + \cos q_3 - \tfrac15\sin 2q_3$, conserved by the exact flow;
    works on saved trajectories (leading axes)."""
    return 0.5 * p[..., 2] ** 2 + jnp.cos(q[..., 2]) - 0.2 * jnp.sin(2 * q[..., 2])


class Gearbox(AbstractExample):
    """The gearbox of §4.4 (no parameters: `args` is `None`); no adapted form, so its
    initial states are $(q, p)$."""

    name: ClassVar[str] = "gearbox"
    title: ClassVar[str] = "the gearbox of §4.4 (Figure 3), from a random state on the constraint"

    @property
    def canonical(self) -> NonholonomicSystem:
        return NonholonomicSystem(_hamiltonian, _constraints)

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem:
        r"""The same system from its Lagrangian $L = \tfrac12|\dot q|^2 - V(q)$
        (`NonholonomicSystem.from_lagrangian`)."""
        return NonholonomicSystem.from_lagrangian(_lagrangian, _constraints)

    @staticmethod
    def constraints(q: Float[Array, "3"], args=None) -> Float[Array, "1 3"]:
        return _constraints(q, args)

    @staticmethod
    def potential(q: Float[Array, "3"], args=None) -> Float[Array, ""]:
        return potential(q, args)

    @staticmethod
    def pendulum_energy(q, p):
        return pendulum_energy(q, p)

    def initial_state(self, seed: int = 0, dtype=None) -> tuple[Array, Array]:
        """`random_initial_state` of the key of `seed`."""
        return self.random_initial_state(jax.random.key(seed), dtype)

    def random_initial_state(self, key: PRNGKeyArray, dtype=None) -> tuple[Array, Array]:
        """q and p uniform in [-1, 1]^3, p projected onto the constraint: a generic
        (non-periodic) state, as in Figure 3."""
        q_key, p_key = jax.random.split(key)
        q = jax.random.uniform(q_key, (3,), dtype=dtype, minval=-1.0, maxval=1.0)
        p = jax.random.uniform(p_key, (3,), dtype=dtype, minval=-1.0, maxval=1.0)
        return q, self.canonical.project_momentum(q, p)


def gearbox() -> Gearbox:
    """The gearbox of §4.4 (see `Gearbox`)."""
    return Gearbox()

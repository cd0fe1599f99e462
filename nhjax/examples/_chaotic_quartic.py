r"""The chaotic quartic nonholonomic system of §4.1 (after McLachlan & Perlmutter).

$q = (x, w_1..w_n, z_1..z_n) \in \mathbb{R}^{2n+1}$, $M = I$,
$V = \tfrac12(|q|^2 + z_1^2 z_2^2 + \sum_i w_i^2 z_i^2)$ (the $z_1^2z_2^2$ coupling needs
$n \ge 2$ and is left out for $n = 1$), constraint (constraint)
$\dot x + \sum_i w_i \dot z_i = 0$. Frame of $\mathcal{D}$: $X_i = \partial_{w_i}$,
$X_{n+i} = w_i\partial_x - \partial_{z_i}$. Adapted state $\zeta = (q, \rho)$ of size
$4n + 1$ with $\mathcal{H} = \tfrac12 \rho^T g^{-1}(w) \rho + V(q)$,
$g^{-1} = \mathrm{diag}(I_n, I_n - ww^T/(1 + w^Tw))$, and the structure (fcseq)
with $\kappa = w^T\eta/(1 + w^Tw)$, $\eta = (\rho_{n+1}, \dots, \rho_{2n})$.
$\nabla\mathcal{H}$ comes from autodiff: the gradient printed in (fcseq) writes $y_i$
for $w_i$ in its $z$ rows.
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._nonholonomic import NonholonomicSystem
from .._system import SkewGradientSystem
from .._adapted import adapted_structure, adapted_to_momentum, momentum_to_adapted
from ._example import AbstractExample


def _split(q):
    n = (q.shape[0] - 1) // 2
    return q[0], q[1 : n + 1], q[n + 1 :]


def _degree(x):
    n, remainder = divmod(x.shape[0] - 1, 4)
    if remainder or n < 1:
        raise ValueError(
            f"The adapted chaotic quartic state has size 4n + 1, got {x.shape[0]}."
        )
    return n


def potential(q, args=None):
    """V(q) of (Lag)."""
    del args
    _, w, z = _split(q)
    coupling = z[0] ** 2 * z[1] ** 2 if z.shape[0] >= 2 else 0.0
    return 0.5 * (q @ q + coupling + jnp.sum(w**2 * z**2))


def _frame(q, args=None):
    del args
    n = (q.shape[0] - 1) // 2
    _, w, _ = _split(q)
    eye, zeros = jnp.eye(n, dtype=q.dtype), jnp.zeros((n, n), q.dtype)
    top = jnp.concatenate([jnp.zeros((1, n), q.dtype), w[None, :]], axis=1)
    return jnp.concatenate(
        [top, jnp.concatenate([eye, zeros], 1), jnp.concatenate([zeros, -eye], 1)], 0
    )


def _hamiltonian(x, args):
    n = _degree(x)
    q, rho = x[: 2 * n + 1], x[2 * n + 1 :]
    _, w, _ = _split(q)
    rho_w, eta = rho[:n], rho[n:]
    kinetic = rho_w @ rho_w + eta @ eta - (w @ eta) ** 2 / (1 + w @ w)
    return 0.5 * kinetic + potential(q, args)


def _structure(x, args):
    n = _degree(x)
    q, rho = x[: 2 * n + 1], x[2 * n + 1 :]
    _, w, _ = _split(q)
    kappa = (w @ rho[n:]) / (1 + w @ w)
    eye, zeros = jnp.eye(n, dtype=x.dtype), jnp.zeros((n, n), x.dtype)
    bracket = jnp.concatenate(
        [jnp.concatenate([zeros, -kappa * eye], 1), jnp.concatenate([kappa * eye, zeros], 1)],
        0,
    )
    return adapted_structure(_frame(q), bracket)


def _canonical_hamiltonian(q, p, args=None):
    return 0.5 * p @ p + potential(q, args)


def _lagrangian(q, qdot, args=None):
    return 0.5 * qdot @ qdot - potential(q, args)


def _constraints(q, args=None):
    del args
    n = (q.shape[0] - 1) // 2
    _, w, _ = _split(q)
    return jnp.concatenate([jnp.ones((1,), q.dtype), jnp.zeros((n,), q.dtype), w])[None, :]


class ChaoticQuartic(AbstractExample):
    """The chaotic quartic system with `n` pairs $(w_i, z_i)$; no parameters
    (`args` is `None`)."""

    n: int = eqx.field(default=3, static=True)

    name: ClassVar[str] = "quartic"
    title: ClassVar[str] = "the chaotic quartic of §4.1 (Figures 1 and 4), n = 3: states of H = 3.06 by an angle"

    def __check_init__(self):
        if not isinstance(self.n, int) or self.n < 1:
            raise ValueError(f"The chaotic quartic needs an integer n >= 1, got {self.n!r}.")

    @property
    def adapted(self) -> SkewGradientSystem:
        """The reduced equations (dynamical) with (fcseq), state size 4n + 1."""
        return SkewGradientSystem(_hamiltonian, _structure)

    @property
    def canonical(self) -> NonholonomicSystem:
        """(Lag)-(constraint) in canonical coordinates: $H = \\tfrac12|p|^2 + V(q)$."""
        return NonholonomicSystem(_canonical_hamiltonian, _constraints)

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem:
        r"""The same system from its Lagrangian (Lag), $L = \tfrac12|\dot q|^2 - V(q)$
        (`NonholonomicSystem.from_lagrangian`)."""
        return NonholonomicSystem.from_lagrangian(_lagrangian, _constraints)

    @staticmethod
    def constraints(q: Float[Array, " 2n+1"], args=None) -> Float[Array, "1 2n+1"]:
        return _constraints(q, args)

    @staticmethod
    def frame(q: Float[Array, " 2n+1"], args=None) -> Float[Array, "2n+1 2n"]:
        return _frame(q, args)

    @staticmethod
    def potential(q: Float[Array, " 2n+1"], args=None) -> Float[Array, ""]:
        return potential(q, args)

    def to_adapted(self, q, p, args=None) -> Float[Array, " 4n+1"]:
        return jnp.concatenate([q, momentum_to_adapted(_frame(q), p)])

    def from_adapted(self, x, args=None) -> tuple[Array, Array]:
        q = x[: 2 * self.n + 1]
        return q, adapted_to_momentum(_frame(q), jnp.eye(q.shape[0], dtype=q.dtype), x[2 * self.n + 1 :])

    def initial_state(self, angle=0.7, dtype=None) -> Float[Array, " 4n+1"]:
        r"""The paper's one-parameter family of states with $H = 3.06$ (n = 3 only):
        $q_0 = (\cos t, 0.6, 0.4, 0.2, 1, 1, 1)$, $\dot q_0 = (0, \sin t, 0, \dots, 0)$,
        which satisfies the constraint for every angle $t$."""
        if self.n != 3:
            raise ValueError(
                f"The H = 3.06 initial states are defined for n = 3, got n = {self.n}."
            )
        angle = jnp.asarray(angle, dtype=dtype)
        zero, one = jnp.zeros_like(angle), jnp.ones_like(angle)
        q = jnp.stack([jnp.cos(angle), 0.6 + zero, 0.4 + zero, 0.2 + zero, one, one, one])
        qdot = jnp.stack([zero, jnp.sin(angle), zero, zero, zero, zero, zero])
        return self.to_adapted(q, qdot)

    def random_initial_states(
        self, key: PRNGKeyArray, count: int, dtype=None
    ) -> Float[Array, "count 4n+1"]:
        """`count` states with H = 3.06 from uniformly random angles (`initial_state`)."""
        angles = jax.random.uniform(key, (count,), maxval=2 * jnp.pi, dtype=dtype)
        return jax.vmap(lambda angle: self.initial_state(angle, dtype))(angles)

    def random_initial_state(self, key: PRNGKeyArray, dtype=None) -> Float[Array, " 4n+1"]:
        """One state of `random_initial_states`."""
        return self.random_initial_states(key, 1, dtype)[0]


def chaotic_quartic(n: int = 3) -> ChaoticQuartic:
    """The chaotic quartic system of §4.1 (see `ChaoticQuartic`)."""
    return ChaoticQuartic(n=n)

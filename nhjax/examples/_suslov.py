r"""The Euler--Poincaré--Suslov problem on $\mathfrak{so}(3)$ of §4.3.

Kinetic Lagrangian with inertia $(I_{ij})$, $I_{12} = 0$, constraint $\omega_3 = 0$
($a = e_3$). On $\mathcal{D}^*$ with $\rho_i = I_{ii}\omega_i$ ($i = 1, 2$):
$\mathcal{H} = \tfrac12(\rho_1^2/I_{11} + \rho_2^2/I_{22})$ and
$\dot\rho = \Pi(\rho)\nabla\mathcal{H}$ with
$\Pi(\rho) = -\begin{pmatrix} 0 & c \\ -c & 0\end{pmatrix}$,
$c = C^1_{12}\rho_1 + C^2_{12}\rho_2$, $C^1_{12} = I_{13}/I_{11}$,
$C^2_{12} = I_{23}/I_{22}$. Equilibria: the line $c = 0$, i.e.
$I_{13}\omega_1 + I_{23}\omega_2 = 0$.
"""

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._system import SkewGradientSystem
from ._example import AbstractExample
from ._parameters import parameters, require_finite, require_positive


_NAME = "Suslov problem"


def _parameters(args):
    """(I11, I22, I13, I23) from `args`."""
    return parameters(args, ("I11", "I22", "I13", "I23"), _NAME)


def _bracket_coefficients(args):
    I11, I22, I13, I23 = _parameters(args)
    return I13 / I11, I23 / I22


def _hamiltonian(rho, args):
    I11, I22, _, _ = _parameters(args)
    return 0.5 * (rho[0] ** 2 / I11 + rho[1] ** 2 / I22)


def _structure(rho, args):
    c1, c2 = _bracket_coefficients(args)
    c = c1 * rho[0] + c2 * rho[1]
    zero = jnp.zeros_like(c)
    return jnp.array([[zero, -c], [c, zero]])


class Suslov(AbstractExample):
    """The Suslov problem with inertia entries `I11`, `I22`, `I13`, `I23` ($I_{12} = 0$;
    $I_{33}$ does not enter the reduced dynamics). State: $(\\rho_1, \\rho_2)$."""

    I11: float = 1.0
    I22: float = 2.0
    I13: float = 0.5
    I23: float = 0.3

    name: ClassVar[str] = "suslov"
    title: ClassVar[str] = (
        "the Suslov problem of §4.3 (a rigid body with one body-frame angular velocity held at zero), "
        "in adapted form only"
    )

    def __check_init__(self):
        require_positive(_NAME, I11=self.I11, I22=self.I22)
        require_finite(_NAME, I13=self.I13, I23=self.I23)

    @property
    def adapted(self) -> SkewGradientSystem:
        return SkewGradientSystem(_hamiltonian, _structure)

    def initial_state(self, omega1=1.0, omega2=0.5, dtype=None) -> Float[Array, "2"]:
        """The state $\\rho = (I_{11}\\omega_1, I_{22}\\omega_2)$ of angular velocity
        $(\\omega_1, \\omega_2, 0)$."""
        return jnp.asarray([self.I11 * omega1, self.I22 * omega2], dtype=dtype)

    def exact_solution(self, t: ArrayLike, rho0: Float[Array, "2"], args=None):
        r"""The exact flow. On the energy ellipse
        $\rho = (\sqrt{2EI_{11}}\cos\psi, \sqrt{2EI_{22}}\sin\psi)$ the equations become
        $\dot\psi = c/\sqrt{I_{11}I_{22}} = A\cos(\psi - \psi_*)$, whose solution with
        $u = \psi - \psi_*$ is $\sin u(t) = \tanh(At + \operatorname{artanh}\sin u_0)$ on
        the half-circle $\cos u > 0$ (and with $A \to -A$, $u \to u - \pi$ on the other)."""
        args = self.args if args is None else args
        i11, i22, _, _ = _parameters(args)
        c1, c2 = _bracket_coefficients(args)
        energy = _hamiltonian(rho0, args)
        semi_axes = jnp.sqrt(2 * energy * jnp.stack([i11, i22]))
        psi0 = jnp.arctan2(rho0[1] / semi_axes[1], rho0[0] / semi_axes[0])
        coefficients = semi_axes * jnp.stack([c1, c2])
        rate = jnp.hypot(coefficients[0], coefficients[1]) / jnp.sqrt(i11 * i22)
        psi_star = jnp.arctan2(coefficients[1], coefficients[0])
        u0 = jnp.angle(jnp.exp(1j * (psi0 - psi_star)))
        back = jnp.abs(u0) > jnp.pi / 2
        shift = jnp.where(back, jnp.pi * jnp.sign(u0), 0.0)
        sign = jnp.where(back, -1.0, 1.0)
        v0 = u0 - shift
        v = jnp.arcsin(jnp.tanh(sign * rate * t + jnp.arctanh(jnp.sin(v0))))
        psi = v + shift + psi_star
        return jnp.stack(
            [semi_axes[0] * jnp.cos(psi), semi_axes[1] * jnp.sin(psi)], axis=-1
        )


def suslov(I11=1.0, I22=2.0, I13=0.5, I23=0.3) -> Suslov:
    """The Suslov problem of §4.3 (see `Suslov`)."""
    return Suslov(I11=I11, I22=I22, I13=I13, I23=I23)

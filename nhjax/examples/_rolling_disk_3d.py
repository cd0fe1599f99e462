r"""Euler's disk: a thin disk rolling without slipping on a horizontal plane, free to
lean, turn and spin (Bloch, *Nonholonomic Mechanics and Control*, 2nd ed., §1.4; Neimark
and Fufaev, *Dynamics of Nonholonomic Systems*, Ch. II).

$q = (x, y, \phi, \theta, \psi)$: the contact point $(x, y)$, the heading $\phi$ (a turn
about the vertical $e_z$), the lean $\theta$ from the vertical (a turn about the
heading's horizontal axis $e_x'$, the line of the disk's plane on the ground) and the
spin $\psi$ (a turn about the axle $e_y''$, normal to the disk). The centre sits at
$r e_z''$ above the contact point, at height $r\cos\theta$. With the mass $m$, the moments
of inertia $J_a$ about the axle and $J_d$ about a diameter (a uniform disk:
$mr^2/2$ and $mr^2/4$) and gravity $g$:

$$L = \tfrac12\dot q^TM(q)\dot q - mgr\cos\theta, \qquad
M = \begin{pmatrix}
m & 0 & mrs_\theta c_\phi & mrs_\phi c_\theta & 0 \\
0 & m & mrs_\phi s_\theta & -mrc_\phi c_\theta & 0 \\
mrs_\theta c_\phi & mrs_\phi s_\theta & (J_a + mr^2)s_\theta^2 + J_dc_\theta^2 & 0 & J_as_\theta \\
mrs_\phi c_\theta & -mrc_\phi c_\theta & 0 & J_d + mr^2 & 0 \\
0 & 0 & J_as_\theta & 0 & J_a
\end{pmatrix}$$

($s_\theta = \sin\theta$, and so on), and rolling without slipping, the material point
at the contact at rest:

$$\dot x - r\cos\phi\,\dot\psi = 0, \qquad \dot y - r\sin\phi\,\dot\psi = 0,$$

$n = 5$, $k = 2$. The metric depends on $q$, and the constraints on $\phi$: a system as
a mechanician derives it (this one with `sympy.physics.mechanics`; the tests check its
motion against sympy's `KanesMethod` equations for the same disk, built independently).

**Steady rolling** (`RollingDisk3D.steady_rolling`): at a constant lean $\theta_0$ and
turning rate $\Omega$, the disk rolls on a circle with a constant spin rate $\omega$
where the lean's acceleration vanishes:

$$(J_a - J_d + mr^2)\,\Omega^2 s_{\theta_0}c_{\theta_0} + (J_a + mr^2)\,\Omega\omega\,c_{\theta_0}
  + mgr\,s_{\theta_0} = 0.$$
"""

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._linalg import solve_spd
from .._nonholonomic import NonholonomicSystem
from ._example import AbstractExample
from ._parameters import parameters, require_positive


_NAME = "3D rolling disk"
_PARAMETERS = ("m", "r", "g", "J_axle", "J_diameter")


def _parameters(args):
    """(m, r, g, J_axle, J_diameter) from `args`."""
    return parameters(args, _PARAMETERS, _NAME)


def _metric(q, args):
    m, r, _, J_a, J_d = _parameters(args)
    phi, theta = q[2], q[3]
    s_phi, c_phi, s_theta, c_theta = jnp.sin(phi), jnp.cos(phi), jnp.sin(theta), jnp.cos(theta)
    zero = jnp.zeros_like(theta)
    a, b = m * r * s_theta * c_phi, m * r * s_phi * s_theta
    c, d = m * r * s_phi * c_theta, -m * r * c_phi * c_theta
    turn = (J_a + m * r**2) * s_theta**2 + J_d * c_theta**2
    return jnp.array(
        [
            [m + zero, zero, a, c, zero],
            [zero, m + zero, b, d, zero],
            [a, b, turn, zero, J_a * s_theta],
            [c, d, zero, J_d + m * r**2 + zero, zero],
            [zero, zero, J_a * s_theta, zero, J_a + zero],
        ]
    )


def _potential(q, args):
    m, r, g, _, _ = _parameters(args)
    return m * g * r * jnp.cos(q[3])


def _hamiltonian(q, p, args):
    return 0.5 * p @ solve_spd(_metric(q, args), p) + _potential(q, args)


def _lagrangian(q, qdot, args):
    return 0.5 * qdot @ (_metric(q, args) @ qdot) - _potential(q, args)


def _constraints(q, args):
    r = _parameters(args)[1]
    phi = q[2]
    zero, one = jnp.zeros_like(phi), jnp.ones_like(phi)
    return jnp.array(
        [[one, zero, zero, zero, -r * jnp.cos(phi)], [zero, one, zero, zero, -r * jnp.sin(phi)]]
    )


class RollingDisk3D(AbstractExample):
    """Euler's disk with mass `m`, radius `r`, gravity `g` and moments of inertia
    `J_axle` and `J_diameter`. Defaults: a uniform disk of unit mass and radius, and
    $g = 1$ (time in units of $\\sqrt{r/g}$). `args` holds the parameters for the
    system's functions."""

    m: float = 1.0
    r: float = 1.0
    g: float = 1.0
    J_axle: float = 0.5
    J_diameter: float = 0.25

    name: ClassVar[str] = "disk-3d"
    title: ClassVar[str] = (
        "Euler's disk, a disk rolling on a plane free to lean, turn and spin (derived with sympy), "
        "from a generic state"
    )

    def __check_init__(self):
        require_positive(_NAME, m=self.m, r=self.r, g=self.g, J_axle=self.J_axle, J_diameter=self.J_diameter)

    @property
    def canonical(self) -> NonholonomicSystem:
        r"""The disk in canonical coordinates, $H = \tfrac12p^TM(q)^{-1}p + mgr\cos\theta$,
        with $M(q)$ written out: a mechanician's $H$ from a mass matrix."""
        return NonholonomicSystem(_hamiltonian, _constraints)

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem:
        """The same system from its Lagrangian (`NonholonomicSystem.from_lagrangian`)."""
        return NonholonomicSystem.from_lagrangian(_lagrangian, _constraints)

    @staticmethod
    def lagrangian(q: Float[Array, "5"], qdot: Float[Array, "5"], args) -> Float[Array, ""]:
        return _lagrangian(q, qdot, args)

    @staticmethod
    def constraints(q: Float[Array, "5"], args) -> Float[Array, "2 5"]:
        """The rolling constraints' matrix A(q): A(q) qdot = 0."""
        return _constraints(q, args)

    @staticmethod
    def metric(q: Float[Array, "5"], args) -> Float[Array, "5 5"]:
        return _metric(q, args)

    def state(self, q, turn_rate, lean_rate, spin_rate, args=None) -> tuple[Array, Array]:
        r"""The state $(q, p)$, $p = M(q)\dot q$, at positions `q` with the rates
        $\dot\phi, \dot\theta, \dot\psi$; the contact point's velocity follows from the
        constraints, $(\dot x, \dot y) = r\dot\psi(\cos\phi, \sin\phi)$."""
        args = self.args if args is None else args
        q = jnp.asarray(q)
        rolling = args["r"] * spin_rate
        qdot = jnp.stack(
            [rolling * jnp.cos(q[2]), rolling * jnp.sin(q[2]), turn_rate + 0 * q[2], lean_rate + 0 * q[2],
             spin_rate + 0 * q[2]]
        ).astype(q.dtype)
        return q, _metric(q, args) @ qdot

    def initial_state(
        self, x=0.3, y=-0.2, heading=0.4, lean=0.25, spin=0.1, turn_rate=0.6, lean_rate=-0.3, spin_rate=2.5, dtype=None
    ) -> tuple[Array, Array]:
        """A generic state (no adapted form: $(q, p)$), by `state`; the defaults lean
        the disk, turn and tip it."""
        q = jnp.asarray([x, y, heading, lean, spin], dtype=dtype)
        return self.state(q, turn_rate, lean_rate, spin_rate)

    def steady_spin_rate(self, lean, turn_rate, args=None):
        r"""The spin rate $\omega$ of steady rolling at lean $\theta_0$ and turning rate
        $\Omega \ne 0$ (the module docstring's condition, for $\cos\theta_0 \ne 0$)."""
        args = self.args if args is None else args
        m, r, g, J_a, J_d = _parameters(args)
        s, c = jnp.sin(lean), jnp.cos(lean)
        return -((J_a - J_d + m * r**2) * turn_rate**2 * s * c + m * g * r * s) / ((J_a + m * r**2) * turn_rate * c)

    def steady_rolling(self, lean, turn_rate, args=None) -> tuple[Array, Array]:
        """The state of steady rolling at lean `lean` and turning rate `turn_rate`, from
        the origin with heading 0: the contact point then runs on a circle."""
        q = jnp.array([0.0, 0.0, 0.0, lean, 0.0])
        return self.state(q, turn_rate, 0.0, self.steady_spin_rate(lean, turn_rate, args), args)


def rolling_disk_3d(m=1.0, r=1.0, g=1.0, J_axle=0.5, J_diameter=0.25) -> RollingDisk3D:
    """Euler's disk (see `RollingDisk3D`)."""
    return RollingDisk3D(m=m, r=r, g=g, J_axle=J_axle, J_diameter=J_diameter)

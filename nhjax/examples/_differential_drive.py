r"""A differential-drive robot: a chassis on two independently driven wheels, the
wheeled robot of every robotics textbook (Siciliano, Sciavicco, Villani & Oriolo,
*Robotics: Modelling, Planning and Control*, Springer 2009, ch. 11, its kinematics and
dynamics with rolling wheels).

$q = (x, y, \theta, \varphi_L, \varphi_R)$: the midpoint of the wheel axle, the heading,
and the angles of the left and right wheels (radius $r$, at $\pm b$ from the midpoint
along the axle). The centre of mass is on the axle's midpoint; the chassis with its
wheels has mass $m$ and moment of inertia $J$ about the vertical, and each wheel $I_w$
about its axle, so

$$L = \tfrac12 m(\dot x^2 + \dot y^2) + \tfrac12 J\dot\theta^2
  + \tfrac12 I_w(\dot\varphi_L^2 + \dot\varphi_R^2),\qquad
  H = \tfrac12 p^TM^{-1}p,\quad M = \operatorname{diag}(m, m, J, I_w, I_w).$$

The wheels roll without slipping, $k = 3$ constraints on $n = 5$ velocities:

$$-\sin\theta\,\dot x + \cos\theta\,\dot y = 0,\qquad
  \cos\theta\,\dot x + \sin\theta\,\dot y \mp b\dot\theta = r\dot\varphi_{L,R}$$

(no sideways slip; each wheel's contact point at rest). The motors apply torques
$u_L(t)$, $u_R(t)$ to the wheels, $F = (0, 0, 0, u_L, u_R)$, and the bearings resist
with viscous friction, $D = \operatorname{diag}(0, 0, 0, c, c)$. The energy balance is
$\dot H = u_L\dot\varphi_L + u_R\dot\varphi_R - c(\dot\varphi_L^2 + \dot\varphi_R^2)$.

**The torques** are piecewise constant: `torques` holds $N$ rows $(u_L, u_R)$, row $i$
applied on $[iT/N, (i + 1)T/N)$ with $T$ = `duration`, the last one held after $T$ (the
control problem of `docs/notebooks/differential_drive_control.ipynb` chooses them).
Fixed steps that divide $T/N$ see each piece whole; a step across a switch is first
order there.

**Closed forms** (from rest at heading 0, one piece). Equal torques $u$ drive straight
ahead with $\dot\varphi = v/r$: $m_e\dot v = 2(u - cv/r)/r$, $m_e = m + 2I_w/r^2$, so
$$v(t) = v_\infty(1 - e^{-t/\tau}),\quad x(t) = v_\infty\big(t - \tau(1 - e^{-t/\tau})\big),
  \quad v_\infty = \frac{ur}{c},\quad \tau = \frac{m_er^2}{2c}.$$
Opposite torques $(-u, u)$ turn it in place, $\dot\varphi_{R,L} = \pm b\omega/r$:
$J_e\dot\omega = 2b(u - cb\omega/r)/r$, $J_e = J + 2I_wb^2/r^2$, so
$\theta(t) = \omega_\infty(t - \tau'(1 - e^{-t/\tau'}))$ with
$\omega_\infty = ur/(cb)$, $\tau' = J_er^2/(2cb^2)$ (`straight_run`, `turn_in_place`).
"""

from typing import ClassVar

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._nonholonomic import NonholonomicSystem
from ._example import AbstractExample
from ._parameters import parameters, require_non_negative, require_positive


_NAME = "differential-drive robot"
_MASSES = ("m", "J", "Iw")


def _masses(args):
    m, J, Iw = parameters(args, _MASSES, _NAME)
    return jnp.stack([m, m, J, Iw, Iw])


def _hamiltonian(q, p, args):
    del q
    return 0.5 * jnp.sum(p**2 / _masses(args).astype(p.dtype))


def _lagrangian(q, qdot, args):
    del q
    return 0.5 * jnp.sum(_masses(args).astype(qdot.dtype) * qdot**2)


def _constraints(q, args):
    r, b = parameters(args, ("r", "b"), _NAME)
    theta = q[2]
    c, s = jnp.cos(theta), jnp.sin(theta)
    zero = jnp.zeros_like(theta)
    r, b = r + zero, b + zero
    return jnp.stack(
        [
            jnp.stack([-s, c, zero, zero, zero]),
            jnp.stack([c, s, -b, -r, zero]),
            jnp.stack([c, s, b, zero, -r]),
        ]
    )


def torque_at(t, torques: Float[Array, "N 2"], duration) -> Float[Array, "2"]:
    """$(u_L, u_R)$ at time `t`: row $\\lfloor tN/T\\rfloor$ of `torques`, the first
    before 0 and the last from $T$ on."""
    torques = jnp.asarray(torques)
    pieces = torques.shape[0]
    index = jnp.clip(jnp.floor(t * pieces / duration).astype(jnp.int32), 0, pieces - 1)
    return torques[index]


def _torques_in_velocities(t, q, qdot, args):
    (torques, duration) = parameters(args, ("torques", "duration"), _NAME)
    wheels = torque_at(t, torques, duration).astype(q.dtype)
    return jnp.concatenate([jnp.zeros(3, q.dtype), wheels])


def _bearing_friction(q, qdot, args):
    (friction,) = parameters(args, ("friction",), _NAME)
    return jnp.diag(jnp.array([0.0, 0.0, 0.0, 1.0, 1.0], q.dtype)) * friction


def _torques(t, q, p, args):
    return _torques_in_velocities(t, q, None, args)


def _bearing_friction_canonical(q, p, args):
    return _bearing_friction(q, None, args)


class DifferentialDrive(AbstractExample):
    """A differential-drive robot (see the module docstring): mass `m`, moment of
    inertia `J` about the vertical through the axle's midpoint, wheel inertia `Iw`,
    wheel radius `r`, half the wheel track `b`, bearing friction `friction`, and the
    piecewise-constant motor torques `torques` (rows $(u_L, u_R)$) over `duration`."""

    m: float = 1.0
    J: float = 0.1
    Iw: float = 0.01
    r: float = 0.1
    b: float = 0.25
    friction: float = 0.02
    torques: Float[Array, "N 2"] | tuple = ((0.05, 0.08),)
    duration: float = 1.0

    name: ClassVar[str] = "differential-drive"
    title: ClassVar[str] = (
        "a two-wheeled robot driven by motor torques against bearing friction, from rest"
    )

    def __check_init__(self):
        require_positive(_NAME, m=self.m, J=self.J, Iw=self.Iw, r=self.r, b=self.b, duration=self.duration)
        require_non_negative(_NAME, friction=self.friction)
        shape = np.shape(self.torques)
        if len(shape) != 2 or shape[1] != 2 or shape[0] < 1:
            raise ValueError(f"The {_NAME}'s torques must be rows (u_L, u_R), shape (N, 2), got shape {shape}.")

    @property
    def canonical(self) -> NonholonomicSystem:
        """$H = \\tfrac12p^TM^{-1}p$, the rolling constraints, the motor torques as
        `force` and the bearing friction as `dissipation`."""
        return NonholonomicSystem(
            _hamiltonian, _constraints, dissipation=_bearing_friction_canonical, force=_torques
        )

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem:
        """The same robot from its Lagrangian, with $D$ and $F$ in velocities."""
        return NonholonomicSystem.from_lagrangian(
            _lagrangian, _constraints, dissipation=_bearing_friction, force=_torques_in_velocities
        )

    def initial_state(self, x=0.0, y=0.0, theta=0.0, dtype=None) -> tuple[Array, Array]:
        """At rest at $(x, y)$ with heading $\\theta$, wheel angles 0."""
        q = jnp.asarray([x, y, theta, 0.0, 0.0], dtype=dtype)
        return q, jnp.zeros_like(q)

    def straight_run(self, torque, t) -> tuple[Array, Array]:
        """$(x(t), v(t))$ from rest at heading 0 under equal torques `torque` on both
        wheels (see the module docstring)."""
        effective = self.m + 2 * self.Iw / self.r**2
        terminal, tau = torque * self.r / self.friction, effective * self.r**2 / (2 * self.friction)
        decay = jnp.exp(-t / tau)
        return terminal * (t - tau * (1 - decay)), terminal * (1 - decay)

    def turn_in_place(self, torque, t) -> tuple[Array, Array]:
        r"""$(\theta(t), \omega(t))$ from rest under torques $(-u, u)$, $u$ = `torque`."""
        effective = self.J + 2 * self.Iw * self.b**2 / self.r**2
        terminal = torque * self.r / (self.friction * self.b)
        tau = effective * self.r**2 / (2 * self.friction * self.b**2)
        decay = jnp.exp(-t / tau)
        return terminal * (t - tau * (1 - decay)), terminal * (1 - decay)


def differential_drive(
    m=1.0, J=0.1, Iw=0.01, r=0.1, b=0.25, friction=0.02, torques=((0.05, 0.08),), duration=1.0
) -> DifferentialDrive:
    """A differential-drive robot (see `DifferentialDrive`)."""
    return DifferentialDrive(m=m, J=J, Iw=Iw, r=r, b=b, friction=friction, torques=torques, duration=duration)

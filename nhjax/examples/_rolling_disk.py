r"""The rolling disk (unicycle) of §2: an upright disk rolling without slipping.

$q = (x_1, x_2, \theta, \phi)$, metric $g = \mathrm{diag}(m, m, J_\theta, J_\phi)$, $V = 0$,
constraints (diskConst) $\dot x_1 - r\dot\phi\cos\theta = 0$,
$\dot x_2 - r\dot\phi\sin\theta = 0$. Frame of $\mathcal{D}$:
$X_1 = r\cos\theta\,\partial_{x_1} + r\sin\theta\,\partial_{x_2} + \partial_\phi$,
$X_2 = \partial_\theta$; all $C^c_{ab} = 0$. Adapted state
$(x_1, x_2, \theta, \phi, \rho_1, \rho_2)$ with
$\mathcal{H} = \tfrac12[\rho_1^2/(mr^2 + J_\phi) + \rho_2^2/J_\theta]$.

**Rolling resistance** (`rolling_resistance` $= c \ge 0$): a viscous torque $-c\dot\phi$
on the rolling angle, the Rayleigh function $\tfrac12c\dot\phi^2$, $D = \operatorname{diag}(0, 0, 0, c)$ (the simplest model of the losses of a rolling wheel). In
the frame, $R = \operatorname{diag}(0, X^TDX) = \operatorname{diag}(0, \dots, c, 0)$ acts on $\rho_1$, so the rolling decays, $\rho_1(t) = \rho_1(0)e^{-kt}$,
$k = c/(mr^2 + J_\phi)$, while the turning rate stays (`exact_solution`). With
$c = 0$ (the default) the system is conservative.
"""

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float, ArrayLike

from .._nonholonomic import NonholonomicSystem
from .._system import SkewGradientSystem
from .._adapted import adapted_structure, adapted_to_momentum, momentum_to_adapted
from ._example import AbstractExample
from ._parameters import is_concrete_zero, parameters, require_non_negative, require_positive


_NAME = "rolling disk"


def _parameters(args):
    """(m, r, J_theta, J_phi) from `args`."""
    return parameters(args, ("m", "r", "J_theta", "J_phi"), _NAME)


def _frame(q, args):
    theta, r = q[2], _parameters(args)[1]
    zero, one = jnp.zeros_like(theta), jnp.ones_like(theta)
    return jnp.array(
        [[r * jnp.cos(theta), zero], [r * jnp.sin(theta), zero], [zero, one], [one, zero]]
    )


def _metric(q, args):
    del q
    m, _, J_theta, J_phi = _parameters(args)
    return jnp.diag(jnp.stack([m, m, J_theta, J_phi]))


def _hamiltonian(x, args):
    rho = x[4:]
    m, r, J_theta, J_phi = _parameters(args)
    rolling_inertia = m * r**2 + J_phi
    return 0.5 * (rho[0] ** 2 / rolling_inertia + rho[1] ** 2 / J_theta)


def _structure(x, args):
    frame = _frame(x[:4], args)
    return adapted_structure(frame, jnp.zeros((2, 2), frame.dtype))


def _canonical_hamiltonian(q, p, args):
    return 0.5 * p @ (p / jnp.diag(_metric(q, args)))


def _lagrangian(q, qdot, args):
    return 0.5 * qdot @ (jnp.diag(_metric(q, args)) * qdot)


def _rolling_resistance(q, qdot, args):
    (resistance,) = parameters(args, ("rolling_resistance",), _NAME)
    return jnp.diag(jnp.array([0.0, 0.0, 0.0, 1.0], q.dtype)) * resistance


def _rolling_resistance_canonical(q, p, args):
    return _rolling_resistance(q, None, args)


def _rolling_resistance_adapted(x, args):
    (resistance,) = parameters(args, ("rolling_resistance",), _NAME)
    return jnp.diag(jnp.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0], x.dtype)) * resistance


def _constraints(q, args):
    theta, r = q[2], _parameters(args)[1]
    zero, one = jnp.zeros_like(theta), jnp.ones_like(theta)
    return jnp.array(
        [[one, zero, zero, -r * jnp.cos(theta)], [zero, one, zero, -r * jnp.sin(theta)]]
    )


class RollingDisk(AbstractExample):
    """The rolling disk with mass `m`, radius `r` and moments of inertia `J_theta`
    (about the vertical axis) and `J_phi` (about the axle). Defaults: a uniform disk of
    unit mass and radius. `args` holds the parameters for the system's functions."""

    m: float = 1.0
    r: float = 1.0
    J_theta: float = 0.25
    J_phi: float = 0.5
    rolling_resistance: float = 0.0

    name: ClassVar[str] = "disk"
    title: ClassVar[str] = "the rolling disk of §2 (a vertical disk rolling on a plane), rolling on a line"

    def __check_init__(self):
        require_positive(_NAME, m=self.m, r=self.r, J_theta=self.J_theta, J_phi=self.J_phi)
        require_non_negative(_NAME, rolling_resistance=self.rolling_resistance)

    def _resists(self) -> bool:
        """Whether the systems carry the rolling resistance: unless it is a concrete 0,
        so that the resistance-free disk is the conservative system itself."""
        return not is_concrete_zero(self.rolling_resistance)

    @property
    def adapted(self) -> SkewGradientSystem:
        """The reduced equations (dynamical) in $(q, \\rho)$, with $R$ on $\\rho_1$ for
        rolling resistance."""
        return SkewGradientSystem(
            _hamiltonian, _structure, dissipation=_rolling_resistance_adapted if self._resists() else None
        )

    @property
    def canonical(self) -> NonholonomicSystem:
        """The disk in canonical coordinates, $H = \\tfrac12 p^T g^{-1} p$, two
        constraints, and the rolling resistance's $D$."""
        return NonholonomicSystem(
            _canonical_hamiltonian,
            _constraints,
            dissipation=_rolling_resistance_canonical if self._resists() else None,
        )

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem:
        r"""The same system from its Lagrangian, the kinetic energy
        $L = \tfrac12(m(\dot x_1^2 + \dot x_2^2) + J_\theta\dot\theta^2 + J_\phi\dot\phi^2)$
        (`NonholonomicSystem.from_lagrangian`), and the Rayleigh function
        $\tfrac12c\dot\phi^2$."""
        return NonholonomicSystem.from_lagrangian(
            _lagrangian, _constraints, dissipation=_rolling_resistance if self._resists() else None
        )

    @staticmethod
    def constraints(q: Float[Array, "4"], args) -> Float[Array, "2 4"]:
        """The constraint matrix A(q) of (diskConst): A(q) qdot = 0."""
        return _constraints(q, args)

    @staticmethod
    def frame(q: Float[Array, "4"], args) -> Float[Array, "4 2"]:
        return _frame(q, args)

    @staticmethod
    def metric(q: Float[Array, "4"], args) -> Float[Array, "4 4"]:
        return _metric(q, args)

    def initial_state(
        self, x1=0.0, x2=0.0, theta=0.0, phi=0.0, rho1=1.0, rho2=0.5, dtype=None
    ) -> Float[Array, "6"]:
        return jnp.asarray([x1, x2, theta, phi, rho1, rho2], dtype=dtype)

    def to_adapted(self, q, p, args=None) -> Float[Array, "6"]:
        args = self.args if args is None else args
        return jnp.concatenate([q, momentum_to_adapted(_frame(q, args), p)])

    def from_adapted(self, x, args=None) -> tuple[Array, Array]:
        args = self.args if args is None else args
        q = x[:4]
        return q, adapted_to_momentum(_frame(q, args), _metric(q, args), x[4:])

    def exact_solution(self, t: ArrayLike, x0: Float[Array, "6"], args=None):
        r"""The exact flow: $\rho_2$ constant and $\theta = \theta_0 + \omega_\theta t$,
        $\omega_\theta = \rho_2/J_\theta \ne 0$; the rolling decays with the resistance,
        $\rho_1 = \rho_1(0)e^{-kt}$, $k = c/(mr^2 + J_\phi)$, $\dot\phi = \omega_\phi e^{-kt}$,
        $\omega_\phi = \rho_1(0)/(mr^2 + J_\phi)$; and the contact point follows
        $\dot x_1 + i\dot x_2 = r\dot\phi\,e^{i\theta}$:
        $$x_1 + ix_2 = x_1(0) + ix_2(0) + r\omega_\phi e^{i\theta_0}\,
          \frac{e^{(i\omega_\theta - k)t} - 1}{i\omega_\theta - k},$$
        which for $k = 0$ is the circle $x_1 = x_1(0) + \tfrac{r\omega_\phi}{\omega_\theta}
        (\sin\theta - \sin\theta_0)$, $x_2 = x_2(0) - \tfrac{r\omega_\phi}{\omega_\theta}
        (\cos\theta - \cos\theta_0)$, evaluated in that form."""
        args = self.args if args is None else args
        x1, x2, theta0, phi0, rho1, rho2 = x0
        m, r, J_theta, J_phi = _parameters(args)
        omega_phi = rho1 / (m * r**2 + J_phi)
        omega_theta = rho2 / J_theta
        theta = theta0 + omega_theta * t
        if not self._resists():
            radius = r * omega_phi / omega_theta
            position = (x1 + radius * (jnp.sin(theta) - jnp.sin(theta0)), x2 - radius * (jnp.cos(theta) - jnp.cos(theta0)))
            phi, rolling = phi0 + omega_phi * t, rho1 + 0 * t
        else:
            decay_rate = parameters(args, ("rolling_resistance",), _NAME)[0] / (m * r**2 + J_phi)
            rate = 1j * omega_theta - decay_rate
            moved = r * omega_phi * jnp.exp(1j * theta0) * jnp.expm1(rate * t) / rate
            position = (x1 + moved.real, x2 + moved.imag)
            decay = jnp.exp(-decay_rate * t)
            phi, rolling = phi0 + omega_phi * -jnp.expm1(-decay_rate * t) / decay_rate, rho1 * decay
        return jnp.stack([*position, theta, phi, rolling, rho2 + 0 * t], axis=-1)


def rolling_disk(m=1.0, r=1.0, J_theta=0.25, J_phi=0.5, rolling_resistance=0.0) -> RollingDisk:
    """The rolling disk of §2 (see `RollingDisk`), with rolling resistance if
    `rolling_resistance` is positive."""
    return RollingDisk(m=m, r=r, J_theta=J_theta, J_phi=J_phi, rolling_resistance=rolling_resistance)

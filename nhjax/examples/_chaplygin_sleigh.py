r"""The Chaplygin sleigh of §4.2: a rigid body on the plane with a knife edge.

$q = (x_1, x_2, \theta)$, kinetic energy with the metric
$\begin{pmatrix} m & 0 & -ma\sin\theta \\ 0 & m & ma\cos\theta \\
-ma\sin\theta & ma\cos\theta & J + ma^2 \end{pmatrix}$, constraint
$-\dot x_1\sin\theta + \dot x_2\cos\theta = 0$. With the blade direction
$u = (-\sin\theta, \cos\theta)$ the metric is $\begin{pmatrix} mI & ma\,u \\
ma\,u^T & J + ma^2\end{pmatrix}$, whose Schur complement is $J$, so
$H = |p_x|^2/2m + (p_\theta - a\,u\cdot p_x)^2/2J$ with $p_x = (p_1, p_2)$: the
canonical form needs no linear solve. Orthonormal frame of $\mathcal{D}$:
$X_1 = \partial_\theta/\sqrt{J + ma^2}$,
$X_2 = (\cos\theta\,\partial_{x_1} + \sin\theta\,\partial_{x_2})/\sqrt{m}$. Adapted state
$(x_1, x_2, \theta, \rho_1, \rho_2)$, $\mathcal{H} = \tfrac12(\rho_1^2 + \rho_2^2)$ and the
structure $\Pi(\theta, \rho_1)$ printed in §4.2, with $C^1_{12} = a\sqrt{m}/(J + ma^2)$.

**Friction along the blade** (`blade_friction` $= c \ge 0$): a viscous force
$-c\,(e\cdot\dot x)\,e$ on the contact point along the blade's direction
$e = (\cos\theta, \sin\theta)$, the Rayleigh function $\tfrac12c\,(e\cdot\dot x)^2$,
$D = c\begin{pmatrix} ee^T & 0 \\ 0 & 0\end{pmatrix}$ (the sideways force is the
constraint's). In the frame, $X_2^TDX_2 = c/m$ and $X_1^TDX = 0$:
$R = \operatorname{diag}(0, 0, 0, 0, c/m)$ acts on $\rho_2$, the momentum along the
blade, and the sleigh comes to rest instead of approaching the straight-line motion of Proposition 4.1. With
$c = 0$ (the default) the system is conservative.
"""

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._nonholonomic import NonholonomicSystem
from .._system import SkewGradientSystem
from .._adapted import adapted_structure, adapted_to_momentum, momentum_to_adapted
from ._example import AbstractExample
from ._parameters import is_concrete_zero, parameters, require_finite, require_non_negative, require_positive


_NAME = "Chaplygin sleigh"


def _parameters(args):
    """(J, a, m) from `args`."""
    return parameters(args, ("J", "a", "m"), _NAME)


def _rotational_inertia(args):
    J, a, m = _parameters(args)
    return J + m * a**2


def _bracket_coefficient(args):
    _, a, m = _parameters(args)
    return a * jnp.sqrt(m) / _rotational_inertia(args)


def _frame(q, args):
    theta = q[2]
    zero = jnp.zeros_like(theta)
    inv_sqrt_m = 1 / jnp.sqrt(_parameters(args)[2])
    return jnp.array(
        [
            [zero, jnp.cos(theta) * inv_sqrt_m],
            [zero, jnp.sin(theta) * inv_sqrt_m],
            [1 / jnp.sqrt(_rotational_inertia(args)) + zero, zero],
        ]
    )


def _metric(q, args):
    theta = q[2]
    _, a, m = _parameters(args)
    zero = jnp.zeros_like(theta)
    return jnp.array(
        [
            [m + zero, zero, -m * a * jnp.sin(theta)],
            [zero, m + zero, m * a * jnp.cos(theta)],
            [-m * a * jnp.sin(theta), m * a * jnp.cos(theta), _rotational_inertia(args) + zero],
        ]
    )


def _hamiltonian(x, args):
    del args
    return 0.5 * (x[3] ** 2 + x[4] ** 2)


def _structure(x, args):
    c = _bracket_coefficient(args) * x[3]
    zero = jnp.zeros_like(c)
    bracket = jnp.array([[zero, -c], [c, zero]])
    return adapted_structure(_frame(x[:3], args), bracket)


def _canonical_hamiltonian(q, p, args):
    J, a, m = _parameters(args)
    theta = q[2]
    along_blade = -jnp.sin(theta) * p[0] + jnp.cos(theta) * p[1]
    return 0.5 * (p[0] ** 2 + p[1] ** 2) / m + 0.5 * (p[2] - a * along_blade) ** 2 / J


def _lagrangian(q, qdot, args):
    return 0.5 * qdot @ _metric(q, args) @ qdot


def _blade_friction(q, qdot, args):
    (friction,) = parameters(args, ("blade_friction",), _NAME)
    e = jnp.stack([jnp.cos(q[2]), jnp.sin(q[2]), jnp.zeros_like(q[2])])
    return friction * jnp.outer(e, e)


def _blade_friction_canonical(q, p, args):
    return _blade_friction(q, None, args)


def _blade_friction_adapted(x, args):
    friction, m = parameters(args, ("blade_friction", "m"), _NAME)
    return jnp.diag(jnp.array([0.0, 0.0, 0.0, 0.0, 1.0], x.dtype)) * (friction / m)


def _constraints(q, args):
    del args
    theta = q[2]
    return jnp.stack([-jnp.sin(theta), jnp.cos(theta), jnp.zeros_like(theta)])[None, :]


class ChaplyginSleigh(AbstractExample):
    """The Chaplygin sleigh with moment of inertia `J` about the centre of mass, mass
    `m`, and distance `a` from the blade's contact point to the centre of mass.
    `args` holds the parameters for the system's functions."""

    J: float = 8.0
    a: float = 1.0
    m: float = 1.0
    blade_friction: float = 0.0

    name: ClassVar[str] = "sleigh"
    title: ClassVar[str] = "the Chaplygin sleigh of §4.2 (Figure 2), from Figure 2's start next to the unstable equilibrium"

    def __check_init__(self):
        require_positive(_NAME, J=self.J, m=self.m)
        require_finite(_NAME, a=self.a)
        require_non_negative(_NAME, blade_friction=self.blade_friction)

    def _rubs(self) -> bool:
        """Whether the systems carry the blade's friction: unless it is a concrete 0, so
        that the frictionless sleigh is the conservative system itself."""
        return not is_concrete_zero(self.blade_friction)

    @property
    def adapted(self) -> SkewGradientSystem:
        """The reduced equations (dynamical) in $(x_1, x_2, \\theta, \\rho_1, \\rho_2)$,
        with $R$ on $\\rho_2$ for friction along the blade."""
        return SkewGradientSystem(_hamiltonian, _structure, dissipation=_blade_friction_adapted if self._rubs() else None)

    @property
    def canonical(self) -> NonholonomicSystem:
        """The sleigh in canonical coordinates, $H = \\tfrac12 p^T M(\\theta)^{-1} p$ with
        the printed metric, and the blade's friction $D$."""
        return NonholonomicSystem(
            _canonical_hamiltonian, _constraints, dissipation=_blade_friction_canonical if self._rubs() else None
        )

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem:
        r"""The same system from its Lagrangian, the kinetic energy
        $L = \tfrac12\dot q^TM(q)\dot q$ (`NonholonomicSystem.from_lagrangian`), and the
        Rayleigh function of the blade's friction."""
        return NonholonomicSystem.from_lagrangian(
            _lagrangian, _constraints, dissipation=_blade_friction if self._rubs() else None
        )

    @staticmethod
    def constraints(q: Float[Array, "3"], args) -> Float[Array, "1 3"]:
        return _constraints(q, args)

    @staticmethod
    def frame(q: Float[Array, "3"], args) -> Float[Array, "3 2"]:
        return _frame(q, args)

    @staticmethod
    def metric(q: Float[Array, "3"], args) -> Float[Array, "3 3"]:
        return _metric(q, args)

    @staticmethod
    def bracket_coefficient(args) -> Float[Array, ""]:
        r"""$C^1_{12} = a\sqrt{m}/(J + ma^2)$: $\dot\rho_1 = -C^1_{12}\rho_1\rho_2$,
        $\dot\rho_2 = C^1_{12}\rho_1^2$ (mom-eq)."""
        return _bracket_coefficient(args)

    def initial_state(
        self, x1=-5.0, x2=0.0, theta=0.1, rho1=0.001, rho2=-0.6, dtype=None
    ) -> Float[Array, "5"]:
        """Defaults: Figure 2's start, next to the unstable equilibrium."""
        return jnp.asarray([x1, x2, theta, rho1, rho2], dtype=dtype)

    def to_adapted(self, q, p, args=None) -> Float[Array, "5"]:
        args = self.args if args is None else args
        return jnp.concatenate([q, momentum_to_adapted(_frame(q, args), p)])

    def from_adapted(self, x, args=None) -> tuple[Array, Array]:
        args = self.args if args is None else args
        q = x[:3]
        return q, adapted_to_momentum(_frame(q, args), _metric(q, args), x[3:])


def chaplygin_sleigh(J=8.0, a=1.0, m=1.0, blade_friction=0.0) -> ChaplyginSleigh:
    """The Chaplygin sleigh of §4.2 (see `ChaplyginSleigh`), with friction along the
    blade if `blade_friction` is positive."""
    return ChaplyginSleigh(J=J, a=a, m=m, blade_friction=blade_friction)

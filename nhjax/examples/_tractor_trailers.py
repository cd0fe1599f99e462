r"""A tractor pulling $N$ trailers down a slope: the $N$-trailer system of mobile
robotics (Laumond, "Controllability of a multibody mobile robot", IEEE Trans. Robot.
Autom. 9 (1993) 755; Sørdalen, "Conversion of the kinematics of a car with $n$ trailers
into a chained form", ICRA 1993), with masses, coasting under gravity. A family of real
systems of any size: $n = N + 3$ coordinates, $k = N + 1$ constraints.

Each body is a cart on one axle, its centre of mass on the axle's midpoint $P_i$; body
$i \ge 1$ is hitched at the midpoint of the axle ahead, at distance $\ell$ behind it
(on-axle hitching). $q = (x, y, \theta_0, \theta_1, \dots, \theta_N)$: the tractor's
midpoint $P_0 = (x, y)$ and the headings, so that
$P_i = P_{i - 1} - \ell(\cos\theta_i, \sin\theta_i)$. With the tractor's mass and moment
of inertia about the vertical $m_0$, $J_0$ and each trailer's $m_1$, $J_1$, on a plane
inclined by `slope` $\alpha$ that falls along $+x$,

$$L = \sum_{i=0}^N\big(\tfrac12m_i|\dot P_i|^2 + \tfrac12J_i\dot\theta_i^2\big)
  + g\sin\alpha\sum_{i=0}^Nm_i\,x_i, \qquad
  M = \begin{pmatrix} \mu_0 & 0 & 0 & \mu_j\ell\sin\theta_j \\
  0 & \mu_0 & 0 & -\mu_j\ell\cos\theta_j \\ 0 & 0 & J_0 & 0 \\
  \cdot & \cdot & 0 & \mu_{\max(j,l)}\ell^2\cos(\theta_j - \theta_l) + \delta_{jl}J_1
  \end{pmatrix}$$

($j, l = 1..N$), with $\mu_j = \sum_{i \ge j}m_i$ the mass from body $j$ back. No axle
slips sideways, $-\sin\theta_i\,\dot x_i + \cos\theta_i\,\dot y_i = 0$ for
$i = 0..N$; with $\dot P_i$ written out, row $i$ of $A(q)$ is

$$\big({-\sin\theta_i},\ \cos\theta_i,\ 0,\
  -\ell\cos(\theta_i - \theta_1), \dots, -\ell\cos(\theta_i - \theta_i), 0, \dots\big),$$

of full rank everywhere (its trailer block is triangular with $-\ell$ on the diagonal).
The velocities allowed are the tractor's speed $v_0$ along its heading and its turning
rate $\dot\theta_0$; trailer $j$ follows by the kinematics of the $N$-trailer system,
$\ell\dot\theta_j = v_{j-1}\sin(\theta_{j-1} - \theta_j)$,
$v_j = v_{j-1}\cos(\theta_{j-1} - \theta_j)$ (`velocity`). The metric depends on $q$
and grows with $N$: `benchmarks/scaling.py` times every method on this family.

**The lone tractor** ($N = 0$) is the knife edge on an inclined plane (Neimark & Fufaev,
*Dynamics of Nonholonomic Systems*, Ch. I): its mass centre on the contact line takes no
torque, $\theta_0 = \theta_0(0) + \omega t$, and $\dot v_0 = g\sin\alpha\cos\theta_0$
(`lone_tractor`).
"""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._linalg import solve_spd
from .._nonholonomic import NonholonomicSystem
from ._example import AbstractExample
from ._parameters import parameters, require_finite, require_positive


_NAME = "tractor with trailers"
_PARAMETERS = ("m_tractor", "J_tractor", "m_trailer", "J_trailer", "hitch", "slope", "g")


def _headings(q):
    """$(\\theta_0, \\dots, \\theta_N)$."""
    return q[2:]


def _tail_masses(trailers: int, m_trailer, dtype):
    r"""$\mu_j = \sum_{i \ge j}m_i$ for $j = 1..N$: $(N - j + 1)m_1$."""
    return m_trailer * jnp.arange(trailers, 0, -1, dtype=dtype)


def _metric(q, args):
    m0, J0, m1, J1, hitch, _, _ = parameters(args, _PARAMETERS, _NAME)
    trailers = q.shape[0] - 3
    angles = _headings(q)[1:]
    tail = _tail_masses(trailers, m1, q.dtype)
    total = m0 + m1 * trailers
    # mu_max(j, l) is the smaller of mu_j and mu_l: mu falls along the train.
    trailer_block = hitch**2 * jnp.minimum(tail[:, None], tail[None, :]) * jnp.cos(
        angles[:, None] - angles[None, :]
    ) + J1 * jnp.eye(trailers, dtype=q.dtype)
    position_block = jnp.stack([tail * hitch * jnp.sin(angles), -tail * hitch * jnp.cos(angles)])
    head = jnp.zeros((3, 3), q.dtype).at[0, 0].set(total).at[1, 1].set(total).at[2, 2].set(J0)
    coupling = jnp.concatenate([position_block, jnp.zeros((1, trailers), q.dtype)])
    return jnp.block([[head, coupling], [coupling.T, trailer_block]])


def _potential(q, args):
    m0, _, m1, _, hitch, slope, g = parameters(args, _PARAMETERS, _NAME)
    trailers = q.shape[0] - 3
    tail = _tail_masses(trailers, m1, q.dtype)
    # sum_i m_i x_i = mu_0 x - l sum_j mu_j cos(theta_j).
    moment = (m0 + m1 * trailers) * q[0] - hitch * tail @ jnp.cos(_headings(q)[1:])
    return -g * jnp.sin(slope) * moment


def _hamiltonian(q, p, args):
    return 0.5 * p @ solve_spd(_metric(q, args), p) + _potential(q, args)


def _lagrangian(q, qdot, args):
    return 0.5 * qdot @ (_metric(q, args) @ qdot) - _potential(q, args)


def _constraints(q, args):
    (hitch,) = parameters(args, ("hitch",), _NAME)
    headings = _headings(q)
    trailers = headings.shape[0] - 1
    # Body i's axle moves with every hitch ahead of it: trailer j <= i.
    ahead = np.arange(trailers)[None, :] < np.arange(trailers + 1)[:, None]
    hitches = jnp.where(ahead, -hitch * jnp.cos(headings[:, None] - headings[None, 1:]), 0.0)
    return jnp.concatenate(
        [-jnp.sin(headings)[:, None], jnp.cos(headings)[:, None], jnp.zeros((trailers + 1, 1), q.dtype), hitches],
        axis=1,
    )


class TractorTrailers(AbstractExample):
    """A tractor (mass `m_tractor`, moment of inertia `J_tractor`) pulling `trailers`
    trailers (each `m_trailer`, `J_trailer`, hitched at distance `hitch`) down a plane
    inclined by `slope` radians under gravity `g` (see the module docstring). The number
    of trailers shapes the system ($n = N + 3$, $k = N + 1$); the rest are `args`."""

    trailers: int = eqx.field(default=3, static=True)
    m_tractor: float = 1.0
    J_tractor: float = 0.2
    m_trailer: float = 0.5
    J_trailer: float = 0.1
    hitch: float = 1.0
    slope: float = 0.2
    g: float = 1.0

    name: ClassVar[str] = "trailers"
    title: ClassVar[str] = (
        "a tractor pulling 3 trailers down a slope, the N-trailer system of mobile robotics with masses"
    )

    def __check_init__(self):
        if isinstance(self.trailers, bool) or not isinstance(self.trailers, int) or self.trailers < 0:
            raise ValueError(f"The {_NAME} needs a whole number of trailers >= 0, got {self.trailers!r}.")
        require_positive(
            _NAME, m_tractor=self.m_tractor, J_tractor=self.J_tractor, m_trailer=self.m_trailer,
            J_trailer=self.J_trailer, hitch=self.hitch, g=self.g,
        )
        require_finite(_NAME, slope=self.slope)

    @property
    def canonical(self) -> NonholonomicSystem:
        r"""$H = \tfrac12p^TM(q)^{-1}p + V(q)$ with $M$ written out."""
        return NonholonomicSystem(_hamiltonian, _constraints)

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem:
        """The same system from its Lagrangian (`NonholonomicSystem.from_lagrangian`)."""
        return NonholonomicSystem.from_lagrangian(_lagrangian, _constraints)

    @staticmethod
    def metric(q: Float[Array, " n"], args) -> Float[Array, "n n"]:
        return _metric(q, args)

    @staticmethod
    def potential(q: Float[Array, " n"], args) -> Float[Array, ""]:
        return _potential(q, args)

    @staticmethod
    def constraints(q: Float[Array, " n"], args) -> Float[Array, "k n"]:
        """The no-slip constraints' matrix A(q): A(q) qdot = 0."""
        return _constraints(q, args)

    def velocity(self, q, speed, turn_rate) -> Float[Array, " n"]:
        r"""$\dot q$ with the tractor's speed `speed` along its heading and turning rate
        `turn_rate`, the trailers' rates by the kinematics of the $N$-trailer system
        (the module docstring)."""
        headings = _headings(q)
        speeds = [jnp.asarray(speed, q.dtype)]
        rates = []
        for j in range(1, headings.shape[0]):
            difference = headings[j - 1] - headings[j]
            rates.append(speeds[-1] * jnp.sin(difference) / self.hitch)
            speeds.append(speeds[-1] * jnp.cos(difference))
        return jnp.stack(
            [speed * jnp.cos(headings[0]), speed * jnp.sin(headings[0]), jnp.asarray(turn_rate, q.dtype), *rates]
        ).astype(q.dtype)

    def initial_state(self, speed=1.0, turn_rate=0.3, heading=0.0, bend=0.3, dtype=None) -> tuple[Array, Array]:
        r"""The tractor at the origin with heading `heading`, trailer $j$ turned by
        $-j\cdot$`bend` from it (the train on an arc), moving at `speed` and turning at
        `turn_rate`: $(q, p)$, $p = M(q)\dot q$ (`velocity`)."""
        angles = heading - bend * jnp.arange(self.trailers + 1)
        q = jnp.asarray(jnp.concatenate([jnp.zeros(2), angles]), dtype=dtype)
        return q, _metric(q, self.args) @ self.velocity(q, speed, turn_rate)

    def lone_tractor(self, t, speed, turn_rate, heading=0.0) -> Float[Array, "5"]:
        r"""$(x, y, \theta_0, v_0, \dot\theta_0)$ at time `t` for $N = 0$, from the origin
        with heading `heading`, speed `speed` and turning rate `turn_rate` $\omega \ne 0$
        (the module docstring): with $c = g\sin\alpha/\omega$ and $a = v_0(0) - c\sin\theta_0(0)$,
        $v_0 = a + c\sin\theta_0$, and $\dot x = v_0\cos\theta_0$,
        $\dot y = v_0\sin\theta_0$ integrated in closed form."""
        if self.trailers != 0:
            raise ValueError(f"The closed form is that of the lone tractor (trailers=0), got trailers={self.trailers}.")
        omega = turn_rate
        c = self.g * np.sin(self.slope) / omega
        start = heading
        theta = start + omega * t
        a = speed - c * np.sin(start)
        x = a * (np.sin(theta) - np.sin(start)) / omega + c * (np.sin(theta) ** 2 - np.sin(start) ** 2) / (2 * omega)
        y = a * (np.cos(start) - np.cos(theta)) / omega + c / omega * (
            (theta - start) / 2 - (np.sin(2 * theta) - np.sin(2 * start)) / 4
        )
        return np.array([x, y, theta, a + c * np.sin(theta), omega])


def tractor_trailers(
    trailers=3, m_tractor=1.0, J_tractor=0.2, m_trailer=0.5, J_trailer=0.1, hitch=1.0, slope=0.2, g=1.0
) -> TractorTrailers:
    """A tractor pulling trailers down a slope (see `TractorTrailers`)."""
    return TractorTrailers(
        trailers=trailers, m_tractor=m_tractor, J_tractor=J_tractor, m_trailer=m_trailer, J_trailer=J_trailer,
        hitch=hitch, slope=slope, g=g,
    )

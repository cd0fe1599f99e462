r"""The nonlinear contact oscillator of McLachlan & Perlmutter (J. Nonlinear Sci. 16, 2006,
§5.2), reversible and gauge-shifted (see `ContactOscillator`)."""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._adapted import adapted_to_momentum, momentum_to_adapted
from .._nonholonomic import NonholonomicSystem
from .._system import SkewGradientSystem
from ._chaotic_quartic import _constraints, _frame, _structure
from ._example import AbstractExample
from ._parameters import require_finite


_NAME = "contact oscillator"


def _potential(q, epsilon):
    x, y, z = q
    return 0.5 * (x**2 + y**2 + z**2 + epsilon * x**2 * z**2)


def _adapted_hamiltonian(state, epsilon):
    q, rho = state[:3], state[3:]
    y = q[1]
    return 0.5 * (rho[0] ** 2 + rho[1] ** 2 / (1 + y**2)) + _potential(q, epsilon)


def _shift(q, gauge):
    r"""$X^T\nabla S$ for $S = \sigma\cos z$: $(0, \sigma\sin z)$ (as $X_2 = y\partial_x - \partial_z$)."""
    return jnp.stack([jnp.zeros_like(q[2]), gauge * jnp.sin(q[2])])


class _CanonicalHamiltonian(eqx.Module):
    """$H(q, p)$ for a coupling fixed at construction: a module, not a closure, so that
    two systems built alike are equal and share one compilation."""

    epsilon: float = eqx.field(static=True)

    def __call__(self, q, p, args):
        return 0.5 * p @ p + _potential(q, self.epsilon)


class _AdaptedHamiltonian(eqx.Module):
    r"""$\mathcal H$ in adapted coordinates, or, with a `gauge`, $\tilde{\mathcal H}$ in
    gauge-shifted ones."""

    epsilon: float = eqx.field(static=True)
    gauge: float | None = eqx.field(static=True, default=None)

    def __call__(self, state, args):
        if self.gauge is not None:
            state = _unshifted(state, self.gauge)
        return _adapted_hamiltonian(state, self.epsilon)


class _ShiftedStructure(eqx.Module):
    r"""$\tilde\Pi = D\varphi\,\Pi\,D\varphi^T$ at $\varphi^{-1}(\tilde\zeta)$."""

    gauge: float = eqx.field(static=True)

    def __call__(self, state, args):
        original = _unshifted(state, self.gauge)
        jacobian = jax.jacfwd(lambda s: _shifted(s, self.gauge))(original)
        return jacobian @ _structure(original, args) @ jacobian.T


def _unshifted(state, gauge):
    q, rho_tilde = state[:3], state[3:]
    return jnp.concatenate([q, rho_tilde + _shift(q, gauge)])


def _shifted(state, gauge):
    q, rho = state[:3], state[3:]
    return jnp.concatenate([q, rho - _shift(q, gauge)])


class ContactOscillator(AbstractExample):
    r"""The nonlinear contact oscillator of McLachlan & Perlmutter (J. Nonlinear Sci. 16, 2006,
    §5.2), in its usual reversible form and in a gauge-shifted form that is integrable but
    not reversible with respect to the standard reversibility map (Modin & Verdier, "What
    makes nonholonomic integrators work?", Numer. Math. 145, 2020).

    $q = (x, y, z)$, $M = I$, $V = \tfrac12(x^2 + y^2 + z^2 + \varepsilon x^2z^2)$, one
    constraint $\dot x + y\dot z = 0$: the chaotic quartic's constraint with $n = 1$
    (`ChaoticQuartic`), with its frame $X_1 = \partial_y$, $X_2 = y\partial_x - \partial_z$
    and its structure (fcseq). The constraint has no $\dot y$ and $V$ no coupling to $y$, so
    $\ddot y = -y$ and, besides $H$, $H_y = \tfrac12(y^2 + \dot y^2)$ is a first integral
    (`y_energy`). For $\varepsilon = 0$ the system is reversible integrable, and its
    invariant tori persist under reversible perturbations such as the $\varepsilon$ term
    (Modin & Verdier, "Integrability of nonholonomically coupled oscillators",
    arXiv:1212.6618): reversible methods keep $H_y$ near its value over long times.

    **The gauge-shifted form** (`ContactOscillator.gauge_shifted`). The momenta
    $\tilde p = p - \nabla S(q)$, $S = \sigma\cos z$, turn $H$ into
    $\tilde H(q, \tilde p) = \tfrac12|\tilde p + \nabla S|^2 + V$, the Legendre transform of
    $L - \langle\nabla S, \dot q\rangle = L - \dot S$: the same motion, since $\dot S$ is a
    total derivative, but $\tilde H(q, -\tilde p) \ne \tilde H(q, \tilde p)$, so
    $(q, \tilde p) \mapsto (q, -\tilde p)$ no longer reverses it. In adapted coordinates
    $\tilde\rho = X^T\tilde p = \rho - X^T\nabla S = (\rho_1, \rho_2 - \sigma\sin z)$, with
    $\tilde{\mathcal H}(\tilde\zeta) = \mathcal H(\varphi^{-1}(\tilde\zeta))$ and the structure
    carried over, $\tilde\Pi = D\varphi\,\Pi\,D\varphi^T$, $\varphi(q, \rho) = (q, \rho - X^T\nabla S)$:
    a skew-gradient system whose exact flow is conjugate to the reversible one by $\varphi$,
    while a discrete-gradient method, which is not invariant under such changes of
    coordinates, gives another map in each. This gauge term with $S = \cos z$ is the one of
    Verdier's odelab package (`NonReversibleContactOscillator`); whether the 2020 paper's
    experiments use exactly this $S$ was not checked, its text not being at hand.
    nhjax's `NonholonomicSystem` takes only Hamiltonians of mechanical type (no term linear
    in $p$), so the gauge-shifted form exists in adapted coordinates only, for
    `nhjax.DiscreteGradient` and the diffrax solvers.

    **Arguments:** `epsilon` ($\varepsilon$, default 0.5) and `gauge` ($\sigma$,
    default 1); `args` is `None`.
    """

    epsilon: float = eqx.field(default=0.5, static=True)
    gauge: float = eqx.field(default=1.0, static=True)

    name: ClassVar[str] = "contact-oscillator"
    title: ClassVar[str] = (
        "McLachlan & Perlmutter's nonlinear contact oscillator (Figure 5), with a second first "
        "integral H_y that reversible methods keep near its value"
    )

    def __check_init__(self):
        # Any real values: a negative epsilon or gauge is another oscillator of the family.
        require_finite(_NAME, epsilon=self.epsilon, gauge=self.gauge)

    @property
    def canonical(self) -> NonholonomicSystem:
        r"""$H = \tfrac12|p|^2 + V(q)$ with $\dot x + y\dot z = 0$."""
        return NonholonomicSystem(_CanonicalHamiltonian(self.epsilon), _constraints)

    @property
    def adapted(self) -> SkewGradientSystem:
        r"""The reduced equations in $\zeta = (q, \rho)$, $\rho = X^Tp$:
        $\mathcal H = \tfrac12(\rho_1^2 + \rho_2^2/(1 + y^2)) + V$ and the structure (fcseq)."""
        return SkewGradientSystem(_AdaptedHamiltonian(self.epsilon), _structure)

    @property
    def gauge_shifted(self) -> SkewGradientSystem:
        r"""The same motion in $\tilde\zeta = (q, \tilde\rho)$,
        $\tilde\rho = \rho - X^T\nabla S$ (see `ContactOscillator`): not reversible under
        $\tilde\rho \mapsto -\tilde\rho$."""
        return SkewGradientSystem(_AdaptedHamiltonian(self.epsilon, self.gauge), _ShiftedStructure(self.gauge))

    def to_adapted(self, q, p, args=None) -> Float[Array, "5"]:
        return jnp.concatenate([q, momentum_to_adapted(_frame(q), p)])

    def from_adapted(self, state, args=None) -> tuple[Array, Array]:
        q = state[:3]
        return q, adapted_to_momentum(_frame(q), jnp.eye(3, dtype=q.dtype), state[3:])

    def to_gauge_shifted(self, state) -> Float[Array, "5"]:
        r"""$\varphi$: adapted coordinates to gauge-shifted ones."""
        return _shifted(state, self.gauge)

    def from_gauge_shifted(self, state) -> Float[Array, "5"]:
        return _unshifted(state, self.gauge)

    @staticmethod
    def y_energy(state) -> Float[Array, "..."]:
        r"""$H_y = \tfrac12(y^2 + \dot y^2)$ from adapted or gauge-shifted states (leading
        axes allowed): $\dot y = \rho_1 = \tilde\rho_1$."""
        return 0.5 * (state[..., 1] ** 2 + state[..., 3] ** 2)

    def initial_state(self, z0=0.5, z_velocity=0.3, energy=1.5, y_energy=0.5, dtype=None) -> Float[Array, "5"]:
        r"""The adapted state $(q, \rho)$ with $y(t) = \sqrt{2H_y}\cos t$: $y_0 = \sqrt{2H_y}$, $\dot y_0 = 0$,
        $z_0$, $\dot z_0$ as given, $\dot x_0 = -y_0\dot z_0$ (the constraint), and
        $x_0 > 0$ from the energy."""
        y0 = jnp.sqrt(2 * jnp.asarray(y_energy, dtype=dtype))
        z0 = jnp.asarray(z0, dtype=y0.dtype)
        z_velocity = jnp.asarray(z_velocity, dtype=y0.dtype)
        x0 = jnp.sqrt((2 * energy - (1 + y0**2) * z_velocity**2 - y0**2 - z0**2) / (1 + self.epsilon * z0**2))
        q = jnp.stack([x0, y0, z0])
        p = jnp.stack([-y0 * z_velocity, jnp.zeros_like(y0), z_velocity])
        return self.to_adapted(q, p)


def contact_oscillator(epsilon: float = 0.5, gauge: float = 1.0) -> ContactOscillator:
    """The contact oscillator of McLachlan & Perlmutter §5.2, with its gauge-shifted form
    (see `ContactOscillator`)."""
    return ContactOscillator(epsilon=epsilon, gauge=gauge)

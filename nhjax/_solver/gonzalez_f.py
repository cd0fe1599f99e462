r"""GONZALEZ-F, eq. (simpDirect): the Gonzalez discrete gradient on $T^*Q$ with
constraint forces."""

from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import optimistix as optx

from .._discrete_gradient import gonzalez, gonzalez_values, midpoint_gradient, with_start_value
from .._nonholonomic import NonholonomicSystem
from .base import (
    AbstractSymmetricSecondOrderMethod,
    check_optional_bool,
    chord_matrix_is_dear,
    increment_scale,
    positive_unit,
    resolution_of,
)


class _StepData(NamedTuple):
    """What the residual of one step needs (`GonzalezF.setup`): $z = (q, p)$ at the
    start and $H(z)$, the step, the scale of the unknowns and the unit of the
    constraint rows."""

    system: NonholonomicSystem
    z: Any
    energy: Any
    h: Any
    scale: Any
    constraint_unit: Any
    args: Any
    midpoint_time: Any


class GonzalezF(AbstractSymmetricSecondOrderMethod):
    r"""GONZALEZ-F, the direct method (simpDirect) on $z = (q, p)$:

    $$\frac{z' - z}{h} = J\,\bar\nabla_2 H(z, z') + \begin{pmatrix} 0 \\ A(\bar q)^T\lambda
      \end{pmatrix},\qquad A(\bar q)\,\bar\nabla_2 H(z, z')_p = 0,$$

    with $\bar q = (q + q')/2$, the Gonzalez discrete gradient `nhjax.gonzalez` of $H$ on
    $\mathbb{R}^{2n}$, and $2n + k$ unknowns $(q', p', \lambda)$. The second equation
    makes the constraint force do no discrete work, so $H(z') = H(z)$ to roundoff; but
    it constrains the discrete-gradient velocity at $\bar q$, not $\partial_pH$ at the
    step's end, so $A(q)\partial_pH(q, p) = 0$ holds only to the method's accuracy.
    Second order and time-symmetric.

    **Dissipation and force.** The momentum equation gains
    $h\big(F(t + \tfrac h2, \bar z) - D(\bar z)\bar v\big)$ with $\bar v = \bar\nabla_2H_p$,
    the discrete-gradient velocity, and $D$, $F$ at the midpoint
    $\bar z = (z + z')/2$ and the step's midpoint time (Celledoni & Høiseth,
    arXiv:1706.08621): as the constraint force does no discrete work,
    $H(z') - H(z) = h\,\bar v^TF - h\,\bar v^TD\bar v$ to roundoff (the step's
    `exchange`), and the step stays symmetric.

    Each step solves for the scaled increment $(z' - z)/s$, $s = 1 + |z|$ (elementwise),
    and the impulse $h\lambda$, with the constraint equation divided by
    $\max|A(q)|\,\max(1 + |\partial_pH(q, p)|)$ at the start so that it is of the size of
    the others (a smaller row, such as one scaled by $h$ or by the size of the positions,
    would amplify its rounding in the impulse through the inverse Jacobian, past the
    root finder's tolerance), from the explicit Euler predictor of the index-1
    equations.

    **Arguments:**

    - `root_finder`, `root_find_max_steps`: as for `nhjax.DiscreteGradient`.
    - `reuse_chord_matrix`: start each step from the last step's chord matrix while
        it serves (`nhjax.AbstractMethod.reuses_chord_matrix`). `None` (default):
        kept where forming it costs several iterations, as for `nhjax.GonzalezR`:
        where the metric depends on $q$ (each of the matrix's $2n + k$ columns is
        then a second derivative of $H$ through $M(q)^{-1}$) or where the unknowns
        are more than `KEPT_ABOVE_UNKNOWNS`; a kept matrix needs about twice the
        iterations. Measured both ways by `benchmarks/chord_reuse.py`: kept, a
        tractor pulling 5, 13 and 29 trailers takes 0.84, 0.52 and 0.33 of the
        time, Euler's disk 0.76, the sleigh 0.86; with a constant metric the
        quartic with $n = 3$ 0.81, but the gearbox 1.25, the contact oscillator
        1.17 and the 2D rolling disk 1.05, whose steps take two iterations with a
        fresh matrix. `True` or `False` to choose.
    """

    term_structure: ClassVar = NonholonomicSystem

    def keeps_energy(self) -> bool:
        return True

    def keeps_constraint(self) -> bool:
        return False

    def summary(self) -> str:
        return '§3.3, the direct method in canonical coordinates'

    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 20
    reuse_chord_matrix: bool | None = None

    def __check_init__(self):
        check_optional_bool("GonzalezF", "reuse_chord_matrix", self.reuse_chord_matrix)

    def reuses_chord_matrix(self, system: NonholonomicSystem, y0, args) -> bool:
        """`reuse_chord_matrix`, or where it is `None`, whether the metric depends on
        $q$ or there are more than `KEPT_ABOVE_UNKNOWNS` unknowns (see the class
        docstring)."""
        if self.reuse_chord_matrix is not None:
            return self.reuse_chord_matrix
        return chord_matrix_is_dear(system, y0, args, lambda n, k: 2 * n + k)

    def composition_obstacle(self) -> str:
        """Symmetric, yet composition does not raise its order: the constraint holds at
        step ends only to O(h^2), and from a state off the constraint the step is not
        close to the identity however small h (the constraint on the discrete-gradient
        velocity moves the momentum by the size of the violation), while the order
        conditions of a composition assume a step that tends smoothly to the identity
        near the solution. Measured on the gearbox: order 1.9 for the order-4 scheme.
        (GONZALEZ-R keeps energy and the constraint exactly, and composes.)"""
        return (
            "GONZALEZ-F does not keep the constraint at step ends, and off the constraint its "
            "step is not close to the identity for small h, so composing it does not raise "
            "its order (measured: still 2); compose GonzalezR, which keeps energy and the "
            "constraint exactly"
        )

    def setup(self, system: NonholonomicSystem, t, h, y0, args, carry):
        del carry
        q, p = y0
        z = jnp.concatenate([q, p])
        scale = increment_scale(z)
        midpoint_time = t + 0.5 * h
        (velocity, acceleration), multiplier = system.field_and_multiplier(midpoint_time, y0, args)
        guess = jnp.concatenate([h * jnp.concatenate([velocity, acceleration]) / scale, h * multiplier])
        constraint_unit = positive_unit(
            jnp.max(jnp.abs(system.constraints(q, args))) * jnp.max(1 + jnp.abs(velocity))
        )
        energy = system.hamiltonian(q, p, args)
        return guess, _StepData(system, z, energy, h, scale, constraint_unit, args, midpoint_time)

    def _equations(self, unknowns, data, discrete_gradient=gonzalez):
        """The residual, and the step's exchange (`exchange`)."""
        system, z, h, scale, args = data.system, data.z, data.h, data.scale, data.args
        (n2,) = z.shape
        n = n2 // 2
        u, impulse = unknowns[:n2], unknowns[n2:]
        z1 = z + scale * u
        hamiltonian = lambda x, args: system.hamiltonian(x[:n], x[n:], args)  # noqa: E731
        # H(z) once a step, not at every iterate (for a Lagrangian, a formation of M).
        gradient = with_start_value(discrete_gradient, data.energy)(hamiltonian, z, z1, args)
        a = system.constraints(0.5 * (z[:n] + z1[:n]), args)
        flow = jnp.concatenate([gradient[n:], -gradient[:n]])
        force = jnp.concatenate([jnp.zeros((n,), z.dtype), a.T @ impulse])
        exchange = None
        if system.is_forced():
            midpoint = 0.5 * (z + z1)
            q_mid, p_mid, velocity = midpoint[:n], midpoint[n:], gradient[n:]
            applied = system.applied_force(data.midpoint_time, q_mid, p_mid, args, velocity)
            flow = flow.at[n:].add(applied)
            supplied, dissipated = system.power_along(data.midpoint_time, q_mid, p_mid, velocity, args)
            exchange = (h * supplied, h * dissipated)
        residual = jnp.concatenate(
            [u - (h * flow + force) / scale, (a @ gradient[n:]) / data.constraint_unit]
        )
        return residual, exchange

    def residual(self, unknowns, data, discrete_gradient=gonzalez):
        return self._equations(unknowns, data, discrete_gradient)[0]

    def residual_and_exchange(self, unknowns, data):
        return self._equations(unknowns, data)

    def exchange(self, unknowns, data):
        r"""$h\,\bar v^TF$ and $h\,\bar v^TD\bar v$, $\bar v = \bar\nabla_2H_p$ (see the
        class docstring)."""
        return self._equations(unknowns, data)[1]

    def root_find_residual(self, unknowns, data):
        return self.residual(unknowns, data, gonzalez_values)

    def simplified_residual(self, unknowns, data):
        """The residual with the midpoint gradient in place of the discrete gradient
        (for the Jacobian approximation, see `nhjax._solver.chord`)."""
        return self.residual(unknowns, data, midpoint_gradient)

    def resolution(self, data):
        n = data.z.shape[0] // 2
        rows = jax.eval_shape(data.system.constraints, data.z[:n], data.args).shape[0]
        impulses = jnp.zeros(rows, data.z.dtype)
        return (
            jnp.concatenate([resolution_of(data.z, data.scale), impulses]),
            jnp.concatenate([data.scale, impulses]),
        )

    def complete(self, unknowns, data):
        n = data.z.shape[0] // 2
        z1 = data.z + data.scale * unknowns[: 2 * n]
        return (z1[:n], z1[n:]), None

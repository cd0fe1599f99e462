r"""SI-DLA: the semi-implicit reversible discrete Lagrange--d'Alembert integrator of
McLachlan & Perlmutter (2006, J. Nonlinear Sci. 16:283, their eq. (4.18)), the first
comparison method of §4.1."""

from typing import Any, ClassVar

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import optimistix as optx

from .._dependence import velocity_depends_on_position
from .._nonholonomic import NonholonomicSystem
from .base import AbstractSymmetricSecondOrderMethod, increment_scale, positive_unit


class _StepData(eqx.Module):
    r"""What the residual of one step needs (`SIDLA.setup`): the step, $q_{1/2}$, the
    normalised $A(q_{1/2})$ and its unit, the units of the impulse and of the velocity
    in the constraint equation, $\partial_qH(q_{1/2}, p_0)$, and which path the step
    takes (`constant_metric`, static: the two paths are different programs). The
    constant-metric path reads the kick $p_0 - h\,\partial_qH(q_{1/2}, p_0)$; the
    general one the start and the scales of its increments."""

    system: NonholonomicSystem
    args: Any
    h: Any
    q_half: Any
    a_half: Any
    a_unit: Any
    p_unit: Any
    v_unit: Any
    force_half: Any
    at_half: Any
    constant_metric: bool = eqx.field(static=True)
    kick: Any = None
    q0: Any = None
    p0: Any = None
    q_scale: Any = None
    p_scale: Any = None
    v0: Any = None
    midpoint_time: Any = None


class SIDLA(AbstractSymmetricSecondOrderMethod):
    r"""SI-DLA, McLachlan & Perlmutter's semi-implicit reversible DLA integrator, their
    eq. (4.18), in canonical coordinates:

    $$\begin{aligned}
      q_{1/2} &= q_0 + \tfrac h2\,\partial_pH(q_0, p_0),\\
      p_1 &= p_0 - \tfrac h2\big[\partial_qH(q_{1/2}, p_0) + \partial_qH(q_{1/2}, p_1)\big]
             + h\,A(q_{1/2})^T\lambda,\\
      q_1 &= q_{1/2} + \tfrac h2\,\partial_pH(q_1, p_1),\\
      0 &= A(q_1)\,\partial_pH(q_1, p_1).
    \end{aligned}$$

    Without constraints and with a constant metric this is the Störmer--Verlet
    (drift-kick-drift) method. The constraint holds at every step end to the root
    finder's tolerance; the energy is not conserved (on the chaotic quartic its error
    is a random walk, variance about $10^{-4}h^4t$). Second order.

    **Time symmetry.** From $(q_1, p_1)$ a step with $-h$ gives
    $q'_{1/2} = q_1 - \tfrac h2\partial_pH(q_1, p_1) = q_{1/2}$; then $(q_0, p_0)$ with
    the same $\lambda$ solves its equations, the last one because the start satisfies
    the constraint.

    **Dissipation and force.** The forced discrete Lagrange--d'Alembert principle
    (Marsden & West, "Discrete mechanics and variational integrators", Acta Numerica
    10 (2001), §3.2, with the midpoint discrete forces $f^\pm = \tfrac h2 F_{ap}$)
    adds to the kick the applied force of the system, $F - Dv$, once over the step:
    $$p_1 = \dots + h\big(F(t + \tfrac h2, q_{1/2}, \bar p) - D(q_{1/2}, \bar p)\,\bar v\big),
      \qquad \bar p = \tfrac12(p_0 + p_1),\quad \bar v = \tfrac12\big(\partial_pH(q_0, p_0)
      + \partial_pH(q_1, p_1)\big) = (q_1 - q_0)/h.$$
    All of it is unchanged by $h \to -h$ with the ends swapped, so the method stays
    symmetric and second order. Its `exchange`, $h\,\bar v^TF$ supplied and
    $h\,\bar v^TD\bar v$ dissipated, is what the discrete force does on the discrete
    displacement $q_1 - q_0$; the energy balance holds to second order, not to
    roundoff. A forced step always takes the general path below ($\bar p$, $\bar v$
    and $F$ make $p_1$ implicit).

    **The implicit structure.** For a $q$-dependent metric the velocity at the end,
    $\partial_pH(q_1, p_1)$, makes the $q$ equation implicit as well, and
    $\partial_qH(q_{1/2}, p_1)$ is quadratic in $p_1$: the step solves for
    $(q_1, p_1, \lambda)$, $2n + k$ unknowns. For a constant metric
    $\partial_pH(q_1, p_1) = \partial_pH(q_{1/2}, p_1)$ and
    $\partial_qH(q_{1/2}, p_1) = \partial_qH(q_{1/2}, p_0)$, so $p_1$ and then $q_1$ are
    explicit (affine) in $\lambda$, and only the $k$ multipliers are unknowns, through
    $A(q_1)$ in the last equation.

    The unknowns are scaled (`nhjax._solver.base.increment_scale`):
    $(q_1 - q_0)/s_q$, $(p_1 - p_0)/s_p$, and the impulse $h\lambda$ measured in units
    of $\max s_p$ with $A$ normalised by $\max|A(q_{1/2})|$ (which leaves the root
    unchanged). The constraint equation is divided by $\max(1 + |\partial_pH(q_0, p_0)|)$,
    so that the root finder's absolute tolerance is a relative one on $A\,\partial_pH$.
    The first step's multiplier guess is the index-1 multiplier at the start; later ones
    take the previous step's.

    **Arguments:**

    - `constant_metric`: `True` takes the $k$-unknown path, `False` the general one,
        `None` (default) decides from the system: the constant path exactly when
        `velocity_depends_on_position` finds that $\partial_pH$ computes nothing from
        $q$ (a trace-time check of the program, not of values at a point, so it holds
        everywhere). `True` on a system with a $q$-dependent metric gives a wrong
        method; `False` is always correct. A forced system takes the general path
        whatever this says.
    - `root_finder`, `root_find_max_steps`: as for `nhjax.DiscreteGradient`.
    """

    term_structure: ClassVar = NonholonomicSystem

    def keeps_energy(self) -> bool:
        return False

    def keeps_constraint(self) -> bool:
        return True

    def summary(self) -> str:
        return "McLachlan & Perlmutter's semi-implicit DLA in canonical coordinates"

    constant_metric: bool | None = eqx.field(default=None, static=True)
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 20

    def __check_init__(self):
        if self.constant_metric not in (None, True, False):
            raise ValueError(
                f"constant_metric must be True, False or None, got {self.constant_metric!r}."
            )

    def metric_is_constant(self, system: NonholonomicSystem, y0, args) -> bool:
        """Whether a step takes the $k$-unknown path (see `constant_metric`)."""
        if self.constant_metric is not None:
            return self.constant_metric
        return not velocity_depends_on_position(system, *y0, args)

    def initial_carry(self, system: NonholonomicSystem, y0, args):
        return system.multiplier(y0, args)

    def setup(self, system: NonholonomicSystem, t, h, y0, args, carry):
        q0, p0 = y0
        v0 = system.velocity(q0, p0, args)
        q_half = q0 + 0.5 * h * v0
        a_half = system.constraints(q_half, args)
        a_unit = positive_unit(jnp.max(jnp.abs(a_half)))
        p_scale = increment_scale(p0)
        p_unit = jnp.max(p_scale)
        v_unit = lax.stop_gradient(jnp.max(1 + jnp.abs(v0)))
        # The multiplier for the normalised constraint matrix A / a_unit is a_unit lambda.
        impulse_guess = h * a_unit * carry / p_unit
        at_half = system.at_position(q_half, args)
        force_half = at_half.position_gradient(p0)
        common = dict(
            system=system,
            args=args,
            h=h,
            q_half=q_half,
            a_half=a_half / a_unit,
            a_unit=a_unit,
            p_unit=p_unit,
            v_unit=v_unit,
            force_half=force_half,
            at_half=at_half,
        )
        if self.metric_is_constant(system, y0, args) and not system.is_forced():
            return impulse_guess, _StepData(**common, constant_metric=True, kick=p0 - h * force_half)
        q_scale = increment_scale(q0)
        # The constant-metric formulas as the predictor: O(h^3) from the root.
        p1 = p0 - h * force_half + common["a_half"].T @ (p_unit * impulse_guess)
        q1 = q_half + 0.5 * h * at_half.velocity(p1)
        guess = jnp.concatenate([(q1 - q0) / q_scale, (p1 - p0) / p_scale, impulse_guess])
        data = _StepData(
            **common,
            constant_metric=False,
            q0=q0,
            p0=p0,
            q_scale=q_scale,
            p_scale=p_scale,
            v0=v0,
            midpoint_time=t + 0.5 * h,
        )
        return guess, data

    def _constant_metric_state(self, u, data: _StepData):
        """$(q_1, p_1)$ from the scaled impulse on the $k$-unknown path."""
        p1 = data.kick + data.a_half.T @ (data.p_unit * u)
        v1 = data.at_half.velocity(p1)
        return data.q_half + 0.5 * data.h * v1, p1, v1

    def _split(self, u, data: _StepData):
        n = data.q0.shape[0]
        q1 = data.q0 + data.q_scale * u[:n]
        p1 = data.p0 + data.p_scale * u[n : 2 * n]
        return q1, p1, u[2 * n :]

    def _constraint(self, q1, v1, data: _StepData):
        a1 = data.system.constraints(q1, data.args) / data.a_unit
        return a1 @ v1 / data.v_unit

    def residual(self, u, data: _StepData):
        if data.constant_metric:
            q1, _, v1 = self._constant_metric_state(u, data)
            return self._constraint(q1, v1, data)
        system, args, h = data.system, data.args, data.h
        q1, p1, impulse = self._split(u, data)
        v1 = system.velocity(q1, p1, args)
        force = data.force_half + data.at_half.position_gradient(p1)
        position = (data.q_half - data.q0 + 0.5 * h * v1) / data.q_scale
        kick = -0.5 * h * force + data.a_half.T @ (data.p_unit * impulse)
        if system.is_forced():
            mean_momentum, mean_velocity = 0.5 * (data.p0 + p1), 0.5 * (data.v0 + v1)
            kick = kick + h * system.applied_force(data.midpoint_time, data.q_half, mean_momentum, args, mean_velocity)
        momentum = kick / data.p_scale
        n = q1.shape[0]
        return jnp.concatenate(
            [u[:n] - position, u[n : 2 * n] - momentum, self._constraint(q1, v1, data)]
        )

    def exchange(self, u, data: _StepData):
        r"""$h\,\bar v^TF$ and $h\,\bar v^TD\bar v$ at $(t + \tfrac h2, q_{1/2}, \bar p)$,
        $\bar v = \tfrac12(v_0 + v_1) = (q_1 - q_0)/h$ (see the class docstring)."""
        system, args = data.system, data.args
        q1, p1, _ = self._split(u, data)
        mean_velocity = 0.5 * (data.v0 + system.velocity(q1, p1, args))
        supplied, dissipated = system.power_along(
            data.midpoint_time, data.q_half, 0.5 * (data.p0 + p1), mean_velocity, args
        )
        return data.h * supplied, data.h * dissipated

    def complete(self, u, data: _StepData):
        if data.constant_metric:
            q1, p1, _ = self._constant_metric_state(u, data)
            impulse = u
        else:
            q1, p1, impulse = self._split(u, data)
        safe_h = jnp.where(data.h == 0, jnp.ones_like(data.h), data.h)
        multiplier = data.p_unit * impulse / (safe_h * data.a_unit)
        return (q1, p1), multiplier

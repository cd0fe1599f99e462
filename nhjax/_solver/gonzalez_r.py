r"""GONZALEZ-R (§3.3): the Gonzalez discrete-gradient method on the reduced system,
evaluated from $H$ and $A$ alone.

**What a step costs.** One chord matrix (`GonzalezR.chord_jacobian`: the derivative of
the field with the frame formed once at the predictor's midpoint, held to first
order and turned along the velocity, from derivatives of $H$ and $A$ and one tangent
through the QR, and its inverse,
`nhjax._solver.chord.chord_inverse`), or the last step's where it is kept
(`reuse_chord_matrix`), then four to eleven residuals at the step sizes of
`benchmarks/gonzalez_r_variants.py`. A residual is the
field at the midpoint, $\Pi\bar\nabla\mathcal{H}$, and $\mathcal{H}$ at $\zeta'$ for the
Gonzalez correction. The field needs the frame only through products with $X$ and
$X^T$ (`nhjax._householder.HouseholderFrame`: $k$ reflections of a vector each) and the
frame's derivative only through products with $J = \partial_q(X^Tp)$ and $J^T$, from
one linearisation of $q \mapsto X(q)^Tp$ applied forward and transposed
(`nhjax._reduced.ReducedSystem.at`): a few passes through the QR, $O(nk^2)$ work, where
forming $J$ takes $n$ tangents of it. For $M = I$, $\mathcal{H}$ and its gradient need
no frame at all (`nhjax._reduced.ReducedSystem`), so the Gonzalez correction costs no
QR. Where $\partial H/\partial p$ does not depend on $q$ (checked on its program),
the metric is a constant (`nhjax._reduced.metric_of`). Under `vmap`
the chord iteration's loop runs until the
slowest trajectory has converged (`benchmarks/gonzalez_r.py` times a batch of 200).
Derivatives of a run add, per step, one
linearisation of the residual (its Jacobian in the unknowns and its derivative along
the data, `nhjax._solver.base._implicit_root`), whose second derivatives of the frame
through the QR in $\Pi$ make most of the derivative program, with the Gonzalez
correction's branch for nearly equal points (`gonzalez_correction`), linearised and
transposed though it runs only where the points nearly coincide. Measured part by part in
the scaling table of `python benchmarks/suite.py` (`benchmarks/_profile.py`), whole
steps against the implicit-midpoint yardstick and the NumPy route by
`python benchmarks/gonzalez_r.py`, against variants of the step by
`python benchmarks/gonzalez_r_variants.py`, derivatives by
`python benchmarks/gradients.py` (results in `benchmarks/results/`).
"""

import math
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from .._discrete_gradient import Branch, gonzalez_correction
from .._linalg import jacobian_by_differences, SEQUENTIAL_BYTES
from .._nonholonomic import NonholonomicSystem
from .._reduced import check_derivative, check_difference_step, Derivative, metric_is, metric_of, ReducedSystem
from .chord import REMAINDER
from .base import (
    AbstractSymmetricSecondOrderMethod,
    agrees,
    check_optional_bool,
    chord_matrix_is_dear,
    displacements_for_step,
    HISTORY,
    increment_scale,
    resolution_of,
    step_key,
    with_displacement,
)


# Up to this many unknowns the exact chord matrix (formed only where it is kept, so at
# few steps) may be formed a column at a time (`GonzalezR._columnwise`,
# `jacobian_by_differences` with `one_at_a_time`): its arrays are then small enough
# that XLA:CPU runs the step's operations in sequence
# (`nhjax._linalg.SEQUENTIAL_BYTES`), which pays at every step. Measured in turns, per
# step: Euler's disk (N = 8, whose N residuals at once carry 8 metrics M(q)) 0.62 of
# the time with its mass matrix, 0.42 from its Lagrangian.
COLUMNWISE_UP_TO = 8


def _extrapolation_weights() -> tuple[int, ...]:
    r"""$w_j = (-1)^j\binom{m}{j + 1}$, $m$ = `HISTORY`: the displacement of the next
    step of one size from those of the last $m$, $\sum_jw_j\delta_j$ (newest first),
    is that of the polynomial of degree $m$ through the last $m + 1$ step ends (a
    vanishing $m$-th difference of the displacements' sums), exact for polynomials of
    degree $m$."""
    return tuple((-1) ** j * math.comb(HISTORY, j + 1) for j in range(HISTORY))


class _Carry(NamedTuple):
    """What a step hands the next (`GonzalezR.initial_carry`)."""

    zeta: Array
    signs: Array
    last_velocity: Array
    earlier_velocity: Array
    last_step: Array
    earlier_step: Array
    displacements: Array


class _StepData(NamedTuple):
    """What the residual of one step needs (`GonzalezR.setup`)."""

    reduced: ReducedSystem
    zeta: Array
    h: Any
    scale: Array
    args: Any
    energy: Array
    momentum: Array | None
    previous_velocity: Array
    previous_step: Array
    midpoint_time: Any
    displacements: Array


class GonzalezR(AbstractSymmetricSecondOrderMethod):
    r"""GONZALEZ-R: energy- and constraint-preserving integration of a
    `NonholonomicSystem` from its $H(q, p)$ and $A(q)$ only (§3.3). One step:

    1. $(q, p) \mapsto \zeta = (q, \rho)$, $\rho = X(q)^T p$ (ptildetop), where $X$ is
       the Householder frame of $\ker A(q)$ with sign choices $s$ taken at $q$ and kept
       for every factorisation in the step;
    2. $\zeta \mapsto \zeta'$ by (E-int) on the reduced system (dynamical),
       $\zeta' - \zeta = h\,\Pi(\bar\zeta)\,\bar\nabla_2\mathcal{H}(\zeta, \zeta')$, with
       the Gonzalez discrete gradient and $\Pi$ at the midpoint
       $\bar\zeta = (\zeta + \zeta')/2$, both from (PiMat), (skewMat), (eq:Htgrad) and
       one frame derivative $\partial X/\partial q(\bar q)$ (see
       `nhjax.NonholonomicSystem.reduced`);
    3. $\zeta' \mapsto (q', p')$, $p' = MX(X^TMX)^{-1}\rho'$ at $q'$ (ptoptilde).

    $H(q', p') = \mathcal{H}(\zeta') = \mathcal{H}(\zeta) = H(q, p)$ and
    $A(q')\partial_pH(q', p') = A(q')X(q')y' = 0$ hold to roundoff. Second order and
    time-symmetric (for a fixed $s$).

    **Arguments:**

    - `derivative`: `"autodiff"` (default; $\partial X/\partial q$ by `jax.jacfwd`
        through the QR, and the exact Gonzalez discrete gradient, with the derivatives
        of its Taylor form for nearly equal points) or `"central_difference"` (the
        paper's remark "Implementation using finite differences": central differences
        of $X$ with increment `difference_step`, default $|h|$; the midpoint gradient
        is then accurate to $O(h^2)$, so the method stays second order and keeps
        energy and constraints, and the correction term's derivatives are its own).
    - `difference_step`: the finite-difference increment, positive, `None` for $|h|$;
        only with `"central_difference"`.
    - `root_finder`, `root_find_max_steps`: as for `nhjax.DiscreteGradient`.
    - `reuse_chord_matrix`: start each step from the last step's chord matrix while
        it serves (`nhjax.AbstractMethod.reuses_chord_matrix`): with the frame held
        fixed the matrix contracts by $O(h)$ whether it is fresh or a step old.
        `None` (default): kept where forming it costs several iterations, that is
        where the metric depends on $q$ (its matrix differentiates $M(q)^{-1}$ along
        each of its $N = 2n - k$ tangents) or where the unknowns are more than
        `KEPT_ABOVE_UNKNOWNS` (an $N \times N$ Jacobian and inverse); `True` or
        `False` to choose. Measured both ways by `benchmarks/chord_reuse.py`: kept,
        Euler's disk takes 0.69 of the time ($H$ from its mass matrix; 0.77 from its
        Lagrangian), a batch of 32 disks under `vmap` 0.89, a tractor pulling 5
        trailers 0.45, the synthetic system of `benchmarks/scaling.py` with $n = 64$
        ($N = 112$) 0.78, with $n = 16$ and $32$ 0.98 and 0.95; the gearbox 1.47 and
        the quartic with $n = 3$ 1.23, where an iteration is dear against a matrix.
        The kept matrix's branch adds to the compilation (about 1.5 s for Euler's
        disk).
    - `exact_chord_matrix`: `False` for `chord_jacobian`'s matrix with the
        frame held, `True` for the Jacobian of the residual without its correction
        term, by forward differences (`nhjax._linalg.jacobian_by_differences`: $N + 1$
        residuals, accurate to $O(\sqrt\varepsilon)$, which changes the contraction
        by as little), which contracts the iteration by $O(h^2)$ (`nhjax._solver.chord`). Which is cheaper
        depends on how far the frame turns within $\mathcal{D}$ and on $N$: at
        $h = 0.1$ with the matrix formed at every step
        (`benchmarks/gonzalez_r_variants.py`) the exact matrix takes a tractor pulling
        5 trailers from 9.0 to 2.7 iterations a step and 0.50 of the time, Euler's
        disk from 10.8 to 6.0 and 0.59, the quartic with $n = 3$ and $10$ 0.83 and
        0.88, but the synthetic system with $n = 16$ 1.54 and the gearbox 1.12. Formed
        by `jax.jacfwd` instead ($N$ tangents through second derivatives of the QR)
        it took 0.61, 1.05, 0.95, 0.95, 1.77 and 1.17 of the time, and compiled longer
        (the tractor 18.2 s against 12.8 s, Euler's disk 13.9 s against 10.5 s).
        The root is the same either
        way, to the iteration's tolerance. `None` (default): the exact matrix where
        the metric depends on $q$ and the matrix is kept (`reuse_chord_matrix` not
        `False`), where its cost is spread over the steps it serves and its faster
        contraction outlasts them; the matrix with the frame held elsewhere.

    **Small motions and wound angles.** For nearly equal $\zeta, \zeta'$ (motion too
    small for the values of $\mathcal{H}$ to resolve: oscillations of amplitude
    $10^{-12}$ about an equilibrium whose energy is of size 1), the difference
    $\mathcal{H}(\zeta') - \mathcal{H}(\zeta)$ comes from gradients along a segment
    (`nhjax.gonzalez`, `nhjax._reduced.ReducedSystem.energy_segment`), and the chord
    iteration's tolerance has a floor at the rounding of the points the residual is
    evaluated at (`resolution`): an angle wound to $6\cdot10^6$ is known to
    $10^{-9}$, and every force that depends on it only to that. The energy of a
    returned state is then kept to its own rounding,
    $\epsilon(|H| + \sum_i|x_i||\partial_iH|)$ per step, which for a wound angle
    exceeds $\epsilon|H|$: storing the angle rounds it.

    **Dissipation and force.** For a system with $D$ and $F$ the reduced system is
    $\dot\zeta = (\Pi - R_\zeta)\nabla\mathcal{H} + g_\zeta$ with
    $R_\zeta = \operatorname{diag}(0, X^TDX)$ and $g_\zeta = (0, X^TF)$
    (`nhjax._reduced.ReducedSystem.dissipation`, `.force`), and step 2 becomes the
    port-Hamiltonian discrete-gradient step of Celledoni & Høiseth
    (arXiv:1706.08621),
    $$\zeta' - \zeta = h\big[\Pi(\bar\zeta)\bar\nabla_2\mathcal{H}
      + \big(0,\ X^T(F(t + \tfrac h2, \bar q, \bar p) - D(\bar q, \bar p)\bar v)\big)\big],
      \qquad \bar v = X\bar\nabla_{2,\rho}\mathcal{H},$$
    with $X$, $\bar p = p(\bar\zeta)$, $D$ and $F$ at the midpoint $\bar\zeta$ and
    the step's midpoint time. Since $\bar\nabla_2\mathcal{H}^T(0, X^Tw) = \bar v^Tw$,
    $$H(q', p') - H(q, p) = h\,\bar v^TF - h\,\bar v^TD\bar v$$
    to roundoff (the step's `exchange`), the constraint holds as without them (the
    $q$-update is unchanged in form), and the step stays symmetric, so second order.
    The chord matrix carries the derivatives of $F - Dv$ in the fixed frame.

    A step whose frame degenerates ($A$ losing rank at $q'$, or between $q$ and $q'$,
    where the frame with the step's signs turns singular) fails with
    `nhjax.RESULTS.constraints_rank_deficient` (`NonholonomicSystem.rank_result`).
    """

    term_structure: ClassVar = NonholonomicSystem

    def keeps_energy(self) -> bool:
        return True

    def keeps_constraint(self) -> bool:
        return True

    def summary(self) -> str:
        return '§3.3, the discrete gradient on the reduced system in canonical coordinates'

    derivative: Derivative = "autodiff"
    difference_step: float | None = None
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 20
    reuse_chord_matrix: bool | None = None
    exact_chord_matrix: bool | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        check_derivative(self.derivative)
        check_difference_step(self.derivative, self.difference_step)
        check_optional_bool("GonzalezR", "reuse_chord_matrix", self.reuse_chord_matrix)
        check_optional_bool("GonzalezR", "exact_chord_matrix", self.exact_chord_matrix)

    def _reduced(self, system, signs, h, y0, args):
        step = None
        if self.derivative == "central_difference":
            step = jnp.abs(h) if self.difference_step is None else self.difference_step
        return ReducedSystem(system, signs, self.derivative, step, metric_of(system, y0, args))

    def initial_carry(self, system: NonholonomicSystem, y0, args):
        r"""What a step hands the next: its $\zeta'$ and sign choices, and the mean
        velocities $(\zeta' - \zeta)/h$ of the last two steps and their signed sizes
        $h$, and the displacements $\zeta' - \zeta$ of the last `HISTORY` steps of one
        size, for the predictors (NaN until there are any)."""
        frame, signs = system.stable_frame(y0[0], args)
        signs = lax.stop_gradient(signs)
        zeta = ReducedSystem(system, signs).to_reduced(y0, args, frame)
        unknown = jnp.full_like(zeta, jnp.nan)
        no_step = jnp.full((), jnp.nan, dtype=zeta.dtype)
        no_history = jnp.full((HISTORY,) + zeta.shape, jnp.nan, zeta.dtype)
        return _Carry(zeta, signs, unknown, unknown, no_step, no_step, no_history)

    def replayed_carry(self, carry: _Carry) -> _Carry:
        r"""$\zeta'$ and the signs: the velocities, step sizes and displacements feed only
        the predictor (`setup`), which a replayed step does not use. Per step of a
        run's derivative they were most of what it stores (the sleigh: 42 of 59
        numbers, with the state and the root)."""
        return carry._replace(
            last_velocity=None, earlier_velocity=None, last_step=None, earlier_step=None, displacements=None
        )

    def setup(self, system: NonholonomicSystem, t, h, y0, args, carry):
        # A step starts from the previous step's zeta' itself, not from
        # zeta = (q, X(q)^T p) recomputed from the (q, p) it returned: the map
        # p -> rho -> p rounds with a bias, which over many steps would drift H. The
        # recomputed zeta is used where that does not apply: when the frame signs change
        # at q, and when y0 is not the state the previous step returned. Either way the
        # q of zeta is q itself, and one factorisation at q gives the signs and the
        # frame that both the recomputed zeta and the start's momentum need.
        q, _ = y0
        frame, signs = system.stable_frame(q, args)
        signs = lax.stop_gradient(signs)
        continues = jnp.all(signs == carry.signs) & jnp.all(carry.zeta[: q.shape[0]] == q)
        reduced = self._reduced(system, signs, h, y0, args)
        zeta = jnp.where(continues, carry.zeta, reduced.to_reduced(y0, args, frame))
        # The predictor: the mean velocity of this step extrapolated linearly from those
        # of the two before, an O(h^2) error in the velocity, so the guess is O(h^3) from
        # the root; otherwise (the first two steps, a restart, a change of signs, in
        # whose frame the carried rho-velocities mean something else) no motion, from
        # which the chord iteration's first iterate, (I - h/2 F)^{-1} h f(zeta), is a
        # linearly implicit Euler step. That iterate costs about what an explicit Euler
        # guess would (started so at every step, 6.07 iterations a step on the gearbox
        # against 4.76 from Euler, `benchmarks/gonzalez_r_variants.py`; in a run only
        # its first steps start so), and its field evaluation is the iteration's own
        # residual, not a second copy of the field in the step's program. The root
        # does not depend on the guess. A step's mean velocity is the velocity at
        # its midpoint to O(h^2), and the midpoints of steps of signed sizes h'', h', h
        # are (h'' + h')/2 and (h' + h)/2 apart: with equal steps the weights are
        # (2, -1); with the unequal and negative substeps of a composition
        # (`nhjax.Composition`) they follow the sizes, and where the two earlier
        # midpoints (nearly) coincide, so that the line through them is ill-determined,
        # the step starts from no motion. Once the last HISTORY steps had this step's
        # size, the displacement is that of the polynomial through the last HISTORY + 1
        # step ends (`_extrapolation_weights`), O(h^(HISTORY + 1)) from the root where
        # the steps are short against the motion, taken where it agrees with the line's
        # (`agrees`): on the gearbox at h = 0.05, Euler's disk at h = 0.01, the sleigh at
        # h = 0.1 and the tractor with three trailers at h = 0.05, 3.1, 3.3, 2.1 and 2.9
        # iterations a step where the line's guess took 3.8, 5.0, 3.0 and 5.1. The
        # substeps of a composition differ in size and keep the line. The guess carries
        # no derivatives (the root's come from the implicit function theorem).
        reach = (h + carry.last_step) / (carry.last_step + carry.earlier_step)
        extrapolates = (
            continues & jnp.all(jnp.isfinite(carry.earlier_velocity)) & (jnp.abs(reach) <= 4)
        )
        extrapolated = carry.last_velocity + reach * (carry.last_velocity - carry.earlier_velocity)
        displacements = displacements_for_step(continues, h, carry.last_step, carry.displacements)
        from_history = jnp.asarray(_extrapolation_weights(), dtype=zeta.dtype) @ displacements / h
        velocity = lax.stop_gradient(
            jnp.where(
                extrapolates & agrees(from_history, extrapolated),
                from_history,
                jnp.where(extrapolates, extrapolated, 0.0),
            )
        )
        midpoint_time = t + 0.5 * h
        scale = increment_scale(zeta)
        guess = h * velocity / scale
        previous = jnp.where(continues, carry.last_velocity, jnp.nan)
        previous_step = jnp.where(continues, carry.last_step, jnp.nan)
        energy, momentum = reduced.start_of_step(zeta, args, frame)
        data = _StepData(
            reduced, zeta, h, scale, args, energy, momentum, previous, previous_step, midpoint_time, displacements
        )
        return guess, data

    def residual(self, u, data, correction: bool = True, branch: Branch = "cond"):
        r"""`correction=False`: the residual with the midpoint gradient alone, for the
        Jacobian approximation (see `nhjax._solver.chord`). `branch`: how the Gonzalez
        correction selects its form for nearly equal points
        (`nhjax._discrete_gradient.gonzalez_correction`), the difference
        $\mathcal{H}(\zeta') - \mathcal{H}(\zeta)$ then coming from gradients along a
        segment (`nhjax._reduced.ReducedSystem.energy_segment`), which is exact to its
        truncation whatever the midpoint gradient, so with either `derivative`."""
        return u - data.h * self._field(u, data, correction, branch)[0] / data.scale

    def residual_and_exchange(self, u, data):
        field, exchange = self._field(u, data)
        return u - data.h * field / data.scale, exchange

    def exchange(self, u, data):
        r"""$h\,\bar v^TF$ and $h\,\bar v^TD\bar v$ with
        $\bar v = X\bar\nabla_\rho\mathcal{H}$, and $X$, $p$, $D$ and $F$ at the
        midpoint (see the class docstring)."""
        return self._field(u, data)[1]

    def _field(self, u, data, correction: bool = True, branch: Branch = "cond"):
        r"""The step's right-hand side $(\zeta' - \zeta)/h$, and its exchange."""
        reduced, zeta, scale, args = data.reduced, data.zeta, data.scale, data.args
        zeta1 = zeta + scale * u
        midpoint = reduced.at(0.5 * (zeta + zeta1), args)
        gradient = midpoint.gradient
        if correction:
            energy1, segment = reduced.energy_segment(zeta, data.momentum, zeta1, args)
            gradient = gonzalez_correction(
                reduced.hamiltonian,
                gradient,
                zeta,
                zeta1,
                args,
                branch=branch,
                taylor=self.derivative == "autodiff",
                f_x=data.energy,
                f_x1=energy1,
                segment=segment,
            )
        field, power = reduced.with_applied_force(
            data.midpoint_time, 0.5 * (zeta + zeta1), midpoint, gradient, midpoint.structure_times(gradient), args
        )
        return field, None if power is None else (data.h * power[0], data.h * power[1])

    def root_find_residual(self, u, data):
        return self.residual(u, data, branch="rarely")

    def reuses_chord_matrix(self, system: NonholonomicSystem, y0, args) -> bool:
        """`reuse_chord_matrix`, or where it is `None`, whether the metric depends on
        $q$ or the reduced system has more than `KEPT_ABOVE_UNKNOWNS` unknowns (see
        the class docstring)."""
        if self.reuse_chord_matrix is not None:
            return self.reuse_chord_matrix
        return chord_matrix_is_dear(system, y0, args, lambda n, k: 2 * n - k)

    def chord_key(self, data):
        """The step size and the frame's signs, for which the chord matrix holds."""
        return step_key(data.h, data.zeta.dtype, data.reduced.signs)

    def simplified_residual(self, u, data):
        return self.residual(u, data, correction=False)

    def chord_remainder(self, data):
        """The chord matrix holds the frame fixed, and the iteration contracts only by
        $O(h)$: it goes on until the error it leaves is below the rounding
        (`nhjax._solver.chord.PresetChord.solve`, `REMAINDER`)."""
        del data
        return REMAINDER

    def chord_jacobian(self, u, data):
        r"""An approximation of the Jacobian of `simplified_residual`,
        $I - \tfrac h2\,S^{-1}FS$ at $\bar\zeta = \zeta + Su/2$, where $F$ is the
        derivative of $\Pi\nabla\mathcal{H}$ with the frame held to first order and
        its turn along the velocity (`nhjax._reduced.ReducedSystem.field_jacobian`
        with `frame_turn`), from derivatives of $H$ and $A$ and one tangent through
        the QR.

        What $F$ leaves out is $O(h)$ in the chord
        iteration's contraction factor, against $O(h^2)$ for the exact matrix, and the
        iteration goes on until the error it leaves is below the rounding
        (`chord_remainder`). Iterations per step at $h = 0.05$, without the turn,
        with it, and with the exact matrix: synthetic systems of
        `benchmarks/scaling.py` at $n = 8$ 8.4, 5.7, 3.9 and $n = 16$ 9.0, 5.9, 4.0;
        $n = 3$ quartic 6.3, 4.9; gearbox 3.9 either way (its frame turns only out of
        $\mathcal{D}$); Euler's disk 9.0, 9.0, 4.6. The exact matrix costs $N + 1$
        residuals, more than the iterations it saves from $n = 16$ on.
        The root does not depend on the matrix, and derivatives of the root do not use
        it (see `nhjax._solver.chord`). With `exact_chord_matrix`, that Jacobian by
        forward differences instead (`nhjax._linalg.jacobian_by_differences`), its
        residuals batched, or one at a time for small systems whose evaluations at all
        $N$ points at once would be large arrays (`_columnwise`)."""
        if self.uses_exact_chord_matrix(data):
            return jacobian_by_differences(
                lambda v: self.simplified_residual(v, data),
                u,
                one_at_a_time=self._columnwise(u, data),
                rows=u.shape[0],
            )
        reduced, zeta, h, scale, args = data.reduced, data.zeta, data.h, data.scale, data.args
        field_jacobian = reduced.field_jacobian(zeta + 0.5 * scale * u, data.midpoint_time, args, frame_turn=True)
        return jnp.eye(u.shape[0], dtype=u.dtype) - (h / scale)[:, None] * field_jacobian * (0.5 * scale)[None, :]

    @staticmethod
    def _columnwise(u, data) -> bool:
        r"""Whether the exact chord matrix is formed a column at a time: with few unknowns
        (`COLUMNWISE_UP_TO`), where its $N$ residuals at once would carry $N$ copies of
        an $n \times n$ metric past `SEQUENTIAL_BYTES`."""
        n = (u.shape[0] + data.reduced.signs.shape[0]) // 2
        return u.shape[0] <= COLUMNWISE_UP_TO and u.shape[0] * n * n * u.dtype.itemsize > SEQUENTIAL_BYTES

    def uses_exact_chord_matrix(self, data) -> bool:
        """`exact_chord_matrix`, or where it is `None`, whether the metric depends on
        $q$ and the matrix may be kept (see the class docstring)."""
        if self.exact_chord_matrix is not None:
            return self.exact_chord_matrix
        return self.reuse_chord_matrix is not False and metric_is(data.reduced.metric, "position")

    def resolution(self, data):
        return resolution_of(data.zeta, data.scale), data.scale

    def complete(self, u, data):
        zeta, scale, args = data.zeta, data.scale, data.args
        signs = data.reduced.signs
        zeta1 = zeta + scale * u
        y1 = data.reduced.from_reduced(zeta1, args)
        # The predictor's data carries no derivatives; zeta' does: the next step
        # starts from it.
        return y1, _Carry(
            zeta=zeta1,
            signs=signs,
            last_velocity=lax.stop_gradient(scale * u / data.h),
            earlier_velocity=lax.stop_gradient(data.previous_velocity),
            last_step=lax.stop_gradient(jnp.asarray(data.h, dtype=zeta.dtype)),
            earlier_step=lax.stop_gradient(data.previous_step),
            displacements=with_displacement(data.displacements, scale * u),
        )

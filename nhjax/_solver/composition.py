r"""Higher order by symmetric composition: any symmetric nhjax method lifted to order 4,
6 or 8, each substep keeping what the method keeps exactly."""

import math
from collections.abc import Sequence
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Int

from .._results import first_failure, RESULTS
from .._system import is_int
from .base import AbstractMethod, AbstractMethodState, MethodState, step_return
from .projection import Projection


def _symmetric(half: Sequence[float]) -> tuple[float, ...]:
    r"""$(\gamma_1, \dots, \gamma_m, \gamma_{m+1}, \gamma_m, \dots, \gamma_1)$ from the
    first $m$, the middle one being $1 - 2\sum_{i \le m}\gamma_i$ so that the sum is 1
    to roundoff."""
    middle = 1.0 - 2.0 * math.fsum(half)
    return (*half, middle, *reversed(half))


# The coefficients as published, the middle one recomputed from the others (it agrees
# with the published value to the digits given).
COMPOSITION_SCHEMES: dict[str, dict] = {
    # Yoshida, Phys. Lett. A 150 (1990); Suzuki, Phys. Lett. A 146 (1990).
    "triple-jump-4": dict(order=4, coefficients=_symmetric([1 / (2 - 2 ** (1 / 3))])),
    # Suzuki, Phys. Lett. A 146 (1990): a smaller error constant than the triple jump.
    "suzuki-4": dict(order=4, coefficients=_symmetric([1 / (4 - 4 ** (1 / 3))] * 2)),
    # Yoshida (1990), solution A; Hairer, Lubich & Wanner, GNI, eq. (V.3.11).
    "yoshida-6": dict(
        order=6,
        coefficients=_symmetric(
            [0.78451361047755726381949763, 0.23557321335935813368479318, -1.17767998417887100694641568]
        ),
    ),
    # Kahan & Li, Math. Comp. 66 (1997); GNI eq. (V.3.12).
    "kahan-li-6": dict(
        order=6,
        coefficients=_symmetric(
            [
                0.39216144400731413927925056,
                0.33259913678935943859974864,
                -0.70624617255763935980996482,
                0.08221359629355080023149045,
            ]
        ),
    ),
    # Suzuki & Umeno (1993), in GNI eq. (V.3.13).
    "suzuki-umeno-8": dict(
        order=8,
        coefficients=_symmetric(
            [
                0.74167036435061295344822780,
                -0.40910082580003159399730010,
                0.19075471029623837995387626,
                -0.57386247111608226665638773,
                0.29906418130365592384446354,
                0.33462491824529818378495798,
                0.31529309239676659663205666,
            ]
        ),
    ),
    # Kahan & Li, Math. Comp. 66 (1997); GNI eq. (V.3.14).
    "kahan-li-8": dict(
        order=8,
        coefficients=_symmetric(
            [
                0.13020248308889008087881763,
                0.56116298177510838456196441,
                -0.38947496264484728640807860,
                0.15884190655515560089621075,
                -0.39590389413323757733623154,
                0.18453964097831570709183254,
                0.25837438768632204729397911,
                0.29501172360931029887096624,
            ]
        ),
    ),
}

# What `order` picks when no coefficients are given.
RECOMMENDED_SCHEMES = {2: None, 4: "suzuki-4", 6: "kahan-li-6", 8: "kahan-li-8"}

# Symmetry and the sum are checked to this: published coefficients carry 20 digits or
# more, and a user's typed to 15 digits are within it.
_COEFFICIENT_TOLERANCE = 1e-12


def _not_composable(solver) -> str:
    """Why a solver that is not an nhjax method cannot be composed."""
    if isinstance(solver, Projection):
        return (
            "A projected step is not symmetric, whatever the solver it wraps: the projection "
            "onto the invariants does not commute with reversing time (nhjax.Projection), so "
            "composition would not raise its order; Projection(diffrax.Dopri8()) is of order 8 "
            "already."
        )
    if isinstance(solver, Composition):
        return (
            "A composition is composed already: compose the method it composes to the order wanted, "
            f"Composition(method, order=...) with order one of {sorted(RECOMMENDED_SCHEMES)}, or give the "
            "coefficients of the whole scheme."
        )
    return "diffrax's explicit Runge-Kutta solvers are not symmetric, and composing them does not raise their order this way."


def _validated_coefficients(coefficients, order) -> tuple[float, ...]:
    try:
        values = tuple(float(c) for c in coefficients)
    except (TypeError, ValueError):
        raise ValueError(f"coefficients must be a sequence of real numbers, got {coefficients!r}.") from None
    if not values or not all(math.isfinite(c) for c in values):
        raise ValueError(f"coefficients must be a non-empty sequence of finite numbers, got {values}.")
    if any(c == 0 for c in values):
        # A substep of size zero is the identity: leaving it out gives the same scheme,
        # while taking it would pose a step's equations with h = 0.
        raise ValueError(f"coefficients must be nonzero (a zero substep does nothing: leave it out), got {values}.")
    asymmetry = max(abs(a - b) for a, b in zip(values, reversed(values)))
    if asymmetry > _COEFFICIENT_TOLERANCE:
        raise ValueError(
            "coefficients must be symmetric, gamma_i = gamma_{s+1-i}, for the composition to "
            f"be symmetric (the order conditions assume it); they differ by up to {asymmetry:.3g}: {values}."
        )
    if abs(math.fsum(values) - 1) > _COEFFICIENT_TOLERANCE:
        raise ValueError(f"coefficients must sum to 1 (consistency), got a sum of {math.fsum(values)!r}: {values}.")
    if not is_int(order) or order < 2 or order % 2:
        raise ValueError(f"order must be an even int >= 2 (a symmetric method has even order), got {order!r}.")
    # Exactly symmetric, so that the composed step is as symmetric as the method.
    return tuple((a + b) / 2 for a, b in zip(values, reversed(values)))


class CompositionState(AbstractMethodState):
    """The diffrax solver state of a `Composition`: the composed method's state, carried
    through every substep, the code of a failed substep and which one it was, and
    root-finder iterations per substep."""

    inner: MethodState
    failure: RESULTS
    failed_substep: Int[Array, ""]
    substep_root_find_steps: Int[Array, " stages"]

    def statistics(self) -> dict[str, Array]:
        """`root_find_steps` (iterations in all), `max_root_find_steps` (the most in one
        substep), `substep_root_find_steps` (iterations in all at each of the $s$
        substeps) and `failed_substep` (the failed substep, counted from 0; -1 if none
        failed)."""
        return dict(
            **self.inner.statistics(),
            substep_root_find_steps=self.substep_root_find_steps,
            failed_substep=self.failed_substep,
        )


class Composition(diffrax.AbstractSolver):
    r"""The symmetric composition of a symmetric method $\Phi_h$ (Hairer, Lubich &
    Wanner, *Geometric Numerical Integration*, 2nd ed., §II.4 and §V.3):

    $$\Psi_h = \Phi_{\gamma_s h} \circ \dots \circ \Phi_{\gamma_1 h}, \qquad
      \gamma_{s+1-i} = \gamma_i, \qquad \sum_i \gamma_i = 1.$$

    With coefficients that satisfy the order conditions, $\Psi_h$ has order 4, 6 or 8
    when $\Phi_h$ is symmetric ($\Phi_{-h} = \Phi_h^{-1}$) of order 2, and is
    symmetric itself. Each substep is a step of `method`, so what `method` keeps
    exactly, `Composition` keeps exactly: energy to roundoff for the discrete-gradient
    methods (`nhjax.DiscreteGradient`, `nhjax.GonzalezR`), and the constraint for
    GONZALEZ-R, SI-DLA, I-DLA and SPARK, at every order. Some $\gamma_i$ are negative:
    those substeps go backwards in time.

    **Schemes** (`COMPOSITION_SCHEMES`; `order` picks the recommended one):

    | name | order $p$ | stages $s$ | $C$ | reference |
    |---|---|---|---|---|
    | `triple-jump-4` | 4 | 3 | 8.5 | Yoshida 1990, Suzuki 1990 |
    | `suzuki-4` | 4 | 5 | 0.11 | Suzuki 1990 (recommended for 4) |
    | `yoshida-6` | 6 | 7 | 0.65 | Yoshida 1990 |
    | `kahan-li-6` | 6 | 9 | 0.0080 | Kahan & Li 1997 (recommended for 6) |
    | `suzuki-umeno-8` | 8 | 15 | 0.0096 | Suzuki & Umeno 1993 |
    | `kahan-li-8` | 8 | 17 | 0.00075 | Kahan & Li 1997 (recommended for 8) |

    $C$ is the measured error constant, error $\approx Ch^p$ at $t = 10$, of the
    composed `nhjax.DiscreteGradient` on the reduced form of the $n = 3$ chaotic
    quartic (`benchmarks/composition.py`; the recommended schemes cost more substeps
    and pay them back: at equal work the error is $(s\,C^{1/p})^p$ times a common factor,
    and $s\,C^{1/p}$ is 2.9 for `suzuki-4` against 5.1 for the triple jump, 4.0 for
    `kahan-li-6` against 6.5 for `yoshida-6`, 6.9 for `kahan-li-8` against 8.4 for
    `suzuki-umeno-8`). Each scheme's order is checked by the tests, by fitting it on the
    paper's systems and on a Lie-algebra model of a symmetric method.

    **A method that is not symmetric** ($\Phi_{-h} \ne \Phi_h^{-1}$), such as
    `nhjax.DiscreteGradient(nhjax.itoh_abe)`, is first made symmetric with its adjoint
    $\Phi^*_h = \Phi_{-h}^{-1}$ (`AbstractMethod.adjoint`): each substep is then
    $\Phi_{\gamma_i h/2} \circ \Phi^*_{\gamma_i h/2}$, symmetric and of order 2 (GNI
    §II.4). A method with neither property is refused, and so is anything that is not an
    nhjax method (diffrax's explicit Runge-Kutta solvers are not symmetric).

    **What a method carries** from step to step (GONZALEZ-R's predictor, the
    multiplier guesses of SI-DLA and I-DLA) passes from substep to substep; the
    GONZALEZ-R predictor extrapolates with the substeps' signed sizes.

    **Dissipation and force.** Substep $i$ starts at $t_0 + (\gamma_1 + \dots +
    \gamma_{i-1})h$, so that a time-dependent force is seen at the substep's own times
    and the composition keeps its order for it, and a forced run's energy ledger gains
    each substep's exchange (`AbstractMethod.exchange`): composed, a discrete-gradient
    method keeps the discrete power balance to roundoff at every order.

    **Arguments:**

    - `method`: a symmetric nhjax method, or one with an adjoint (see above). GONZALEZ-F
        is refused: symmetric, but not close to the identity off the constraint, which
        it does not keep, so composition leaves it at order 2
        (`AbstractMethod.composition_obstacle`).
    - `order`: 2, 4, 6 or 8, the recommended scheme of that order (2: `method` itself,
        or its symmetrisation); with `coefficients`, the order they are claimed to have,
        an even int.
    - `coefficients`: the $\gamma_i$ of another scheme, e.g.
        `Composition(method, **COMPOSITION_SCHEMES["suzuki-umeno-8"])`; they must be
        symmetric and sum to 1 (to $10^{-12}$; a `ValueError` otherwise). nhjax cannot
        check the order conditions on construction: the order is what the caller claims.

    **Statistics and failures.** `nhjax.Solution.stats` gains `substep_root_find_steps`
    (root-finder iterations at each substep, summed over the steps) and
    `failed_substep` (which substep failed, from 0; -1 if none did); a failed substep
    fails the step with its own `nhjax.RESULTS` code, and `nhjax.integrate`'s error
    message names the substep.
    """

    interpolation_cls: ClassVar = diffrax.LocalLinearInterpolation
    # The orders `order` takes (each with its recommended scheme).
    orders: ClassVar[tuple[int, ...]] = tuple(RECOMMENDED_SCHEMES)

    @classmethod
    def recommended_scheme(cls, order: int) -> tuple[str | None, int]:
        """The scheme `order` picks: its name in `COMPOSITION_SCHEMES` (`None` at order
        2, the method itself) and its substeps per step."""
        scheme = RECOMMENDED_SCHEMES[order]
        return scheme, 1 if scheme is None else len(COMPOSITION_SCHEMES[scheme]["coefficients"])

    # Not a `diffrax.AbstractWrappedSolver` (as `nhjax.Projection` is): a wrapper passes
    # `isinstance` checks as what it wraps, and a composition would pass as an
    # `AbstractMethod` whose one-root step it does not have (its step is `stages` root
    # finds, of another order, with statistics of its own).
    method: AbstractMethod
    scheme_order: int = eqx.field(static=True)
    coefficients: tuple[float, ...] = eqx.field(static=True)

    def __init__(self, method: AbstractMethod, order: int = 4, *, coefficients: Sequence[float] | None = None):
        if not isinstance(method, AbstractMethod):
            raise ValueError(
                "Composition composes nhjax methods, whose steps solve for a signed step "
                f"size; got {type(method).__name__}. " + _not_composable(method)
            )
        if not method.is_symmetric() and method.adjoint() is None:
            raise ValueError(
                f"{type(method).__name__} is not symmetric (its step with -h does not undo "
                "its step with h) and has no adjoint to symmetrise it with, so composition "
                "would not raise its order. Override `is_symmetric` (or `adjoint`) if it is."
            )
        obstacle = method.composition_obstacle()
        if obstacle is not None:
            raise ValueError(f"Composition refuses {type(method).__name__}: {obstacle}.")
        if coefficients is None:
            if order not in RECOMMENDED_SCHEMES or not is_int(order):
                raise ValueError(
                    f"order must be one of {sorted(RECOMMENDED_SCHEMES)} (or give coefficients), got {order!r}."
                )
            scheme = RECOMMENDED_SCHEMES[order]
            coefficients = (1.0,) if scheme is None else COMPOSITION_SCHEMES[scheme]["coefficients"]
        self.method = method
        self.coefficients = _validated_coefficients(coefficients, order)
        self.scheme_order = int(order)

    @property
    def term_structure(self):
        return self.method.term_structure

    @property
    def stages(self) -> int:
        return len(self.coefficients)

    def order(self, terms):
        """The scheme's order, or the method's if that is higher; `None` if the method's
        order is unknown."""
        method_order = self.method.order(terms)
        return None if method_order is None else max(self.scheme_order, method_order)

    def keeps_energy(self) -> bool:
        return self.method.keeps_energy()

    def keeps_constraint(self) -> bool:
        return self.method.keeps_constraint()

    def is_symmetric(self) -> bool:
        return True

    def summary(self) -> str:
        return f"{self.method.summary()}, composed to order {self.scheme_order} (nhjax.Composition)"

    def _symmetric_method(self) -> tuple[AbstractMethod, AbstractMethod | None]:
        """The method and, where it is not symmetric, its adjoint."""
        if self.method.is_symmetric():
            return self.method, None
        return self.method, self.method.adjoint()

    def init(self, terms, t0, t1, y0, args) -> CompositionState:
        inner = self.method.init(terms, t0, t1, y0, args)
        return CompositionState(
            inner=inner,
            failure=RESULTS.successful,
            failed_substep=jnp.array(-1, dtype=jnp.int32),
            substep_root_find_steps=jnp.zeros(self.stages, dtype=jnp.int32),
        )

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def _substep(self, system, t, h, y, args, inner: MethodState):
        method, adjoint = self._symmetric_method()
        if adjoint is None:
            return method.advance(system, t, h, y, args, inner)
        y_half, inner, first = adjoint.advance(system, t, 0.5 * h, y, args, inner)
        y1, inner, second = method.advance(system, t + 0.5 * h, 0.5 * h, y_half, args, inner)
        return y1, inner, first_failure(first, second)

    def step(self, terms, t0, t1, y0, args, solver_state: CompositionState, made_jump):
        del made_jump
        system, h = AbstractMethod.system_and_step(terms, t0, t1)
        coefficients = jnp.asarray(self.coefficients, dtype=jnp.result_type(h))
        sizes = h * coefficients
        # Each substep starts where the ones before it ended, so that a time-dependent
        # force is seen at the right times and the order holds for it too.
        starts = t0 + h * (jnp.cumsum(coefficients) - coefficients)

        def substep(state, size_and_index):
            y, inner, failure, failed_substep = state
            size, start, index = size_and_index
            y1, inner1, substep_failure = self._substep(system, start, size, y, args, inner)
            # After a failure the remaining substeps run on (a scan cannot stop), but
            # count for nothing and cannot change the code.
            ran = failure == RESULTS.successful
            newly_failed = ran & (substep_failure != RESULTS.successful)
            steps = jnp.where(ran, inner1.total_steps - inner.total_steps, 0)
            inner1 = jax.tree.map(lambda new, old: jnp.where(ran, new, old), inner1, inner)
            state = (y1, inner1, first_failure(failure, substep_failure), jnp.where(newly_failed, index, failed_substep))
            return state, steps

        initial = (y0, solver_state.inner, RESULTS.successful, solver_state.failed_substep)
        indices = jnp.arange(self.stages, dtype=jnp.int32)
        (y1, inner, failure, failed_substep), steps = lax.scan(substep, initial, (sizes, starts, indices))
        state = CompositionState(
            inner=inner,
            failure=failure,
            failed_substep=failed_substep,
            substep_root_find_steps=solver_state.substep_root_find_steps + steps,
        )
        return step_return(y0, y1, state, failure)

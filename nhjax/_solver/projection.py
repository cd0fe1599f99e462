r"""Projection onto the invariants: any diffrax solver, each step's end projected back
onto the energy level of the start (for a forced system, onto the energy balance) and
onto the constraint."""

from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, Int, PyTree, Scalar

from .._ledger import Ledgered
from .._linalg import inverse
from .._nonholonomic import NonholonomicSystem
from .._results import first_failure, RESULTS
from .._system import AbstractSystem
from .base import (
    _implicit_root,
    AbstractCountingState,
    all_finite,
    check_positive_int,
    default_root_finder,
    is_nhjax_solver,
    no_gradient,
    ROUNDING_FLOOR,
    step_return,
    unwrapped_system,
)
from .chord import PresetChord


class ProjectionState(AbstractCountingState):
    """The diffrax solver state of a `Projection`: the projection's iteration counts,
    the wrapped solver's state, the energy level every step is projected onto (the
    energy at the start of the run), and the code of the step that failed, if one
    did."""

    inner: PyTree
    energy: Scalar
    failure: RESULTS


class _ProjectionData(eqx.Module):
    """What the projection's equations need: the unprojected end $\\tilde y$ (flat),
    the scaled invariants' Jacobian there, the energy level, and the row scales."""

    system: AbstractSystem
    unravel: Any = eqx.field(static=True)
    y_tilde: Float[Array, " N"]
    directions: Float[Array, "r N"]
    energy: Scalar
    scales: Float[Array, " r"]
    args: PyTree


def _invariants(system: AbstractSystem, y, args, energy) -> Float[Array, " r"]:
    r"""$g(y)$, zero on the invariant set: $H(y) - H_0$, and for a `NonholonomicSystem`
    also the constraint $A(q)\,\partial_pH(q, p)$."""
    if isinstance(system, NonholonomicSystem):
        # H and A dH/dp from one evaluation of H and its gradient (`observables`): a
        # system given by its Lagrangian forms M(q) once for both.
        observed = system.observables(y, args)
        return jnp.concatenate([jnp.reshape(observed["energy"] - energy, (1,)), observed["constraint"]])
    return jnp.reshape(system.energy(y, args) - energy, (1,))


def _row_scales(system: AbstractSystem, y, args, energy) -> Float[Array, " r"]:
    r"""The units in which each invariant's residual is measured: $1 + |H_0|$ for the
    energy, and $|A|\,(1 + |\partial_pH|)$ (max norms) for the constraint, the size
    of the rounding in $A(q)\,\partial_pH$."""
    energy_scale = jnp.reshape(1 + jnp.abs(energy), (1,))
    if isinstance(system, NonholonomicSystem):
        q, p = y
        a = system.constraints(q, args)
        size = jnp.max(jnp.abs(a)) * (1 + jnp.max(jnp.abs(system.velocity(q, p, args))))
        constraint_scale = jnp.broadcast_to(jnp.where(size > 0, size, 1), (a.shape[0],))
        return lax.stop_gradient(jnp.concatenate([energy_scale, constraint_scale]))
    return lax.stop_gradient(energy_scale)


def _level(system: AbstractSystem, y0, args) -> Scalar:
    """The energy every step is projected onto, less the ledger's balance for a forced
    run: $H(y_0) - (W_0 - D_0)$, so that a step's end is projected onto
    $H = H(y_0) + (W_1 - W_0) - (D_1 - D_0)$."""
    if isinstance(y0, Ledgered):
        return system.energy(y0.state, args) - (y0.work - y0.dissipated)
    return system.energy(y0, args)


def _residual(multipliers, data: _ProjectionData):
    y = data.unravel(data.y_tilde + data.directions.T @ multipliers)
    return _invariants(data.system, y, data.args, data.energy) / data.scales


class Projection(diffrax.AbstractWrappedSolver):
    r"""A diffrax solver whose every step ends on the invariant set: the energy level of
    the run's initial state and, for a `NonholonomicSystem`, the constraint
    $A(q)\,\partial_pH = 0$ (standard projection, Hairer, Lubich & Wanner, *Geometric
    Numerical Integration*, 2nd ed., §IV.4, Algorithm 4.2).

    A step of `solver` gives $\tilde y_1$; the step returns
    $$y_1 = \tilde y_1 + G(\tilde y_1)^T\mu,\qquad g(y_1) = 0,\qquad
      g(y) = \big(H(y) - H(y_0),\ A(q)\,\partial_pH(q, p)\big),$$
    $G = \partial g/\partial y$ (rows scaled to the rounding of each invariant), $\mu$
    from the simplified Newton iteration
    $\mu \leftarrow \mu - (G G^T)^{-1} g(\tilde y_1 + G^T\mu)$, whose matrix is the exact
    Jacobian at $\mu = 0$: from $\tilde y_1$, which is off the set by the solver's local
    error, one correction and one check reach the rounding floor. The projection moves
    $\tilde y_1$ by $O(|g(\tilde y_1)|)$, the local error, so $y_1$ keeps the solver's
    order (GNI Theorem IV.4.2), and energy and constraint hold to roundoff at every
    step, without drift over long runs. With `Projection(diffrax.Dopri8())` under
    `nhjax.integrate_adaptive` this is the cheapest high-order route to exact
    invariants (`benchmarks/composition.py`).

    **What it does not keep.** The projected method is neither symmetric nor
    reversible, whatever `solver` is: it has none of the long-time behaviour that
    symmetry gives the compositions of the discrete-gradient methods
    (`nhjax.Composition`) on reversible systems, such as bounded errors in the other
    first integrals of integrable problems (GNI §IV.4, Example 4.4, and §XI). It keeps
    exactly what it projects onto and nothing else.

    **Dissipation and force.** For a system with a force or a dissipation the energy
    is not kept but balanced: the run carries its energy ledger, the work $W$ supplied
    and the energy $D$ dissipated (`nhjax._ledger`), as extra state integrated by
    `solver` with the system, and each step's end is projected onto the energy
    balance and the constraint,
    $$g(y) = \big(H(y) - H(y_0) - (W_1 - D_1),\ A(q)\,\partial_pH(q, p)\big),$$
    with $W_1$, $D_1$ the ledger at the step's end, which the projection leaves as it
    is. The balance then holds to roundoff at every step, and the ledger, the state
    and so the energy to `solver`'s order. Outside a run that carries the ledger
    (`nhjax.integrate`, `nhjax.integrate_adaptive`) a forced system is refused: its
    initial energy level is not an invariant.

    **Steps, saves and derivatives.** The step-size controller sees `solver`'s error
    estimate of $\tilde y_1$. The interpolation between step ends is linear (the
    solver's dense output describes $\tilde y$), so `nhjax.integrate_adaptive` makes
    every saved time a step end. A solver that carries the field at the step's end into
    the next step (first same as last: `diffrax.Tsit5`, `diffrax.Dopri5`) is
    re-initialised at $y_1$, one field evaluation per step more. Derivatives of $\mu$
    come from the implicit function theorem (`nhjax._solver.base._implicit_root`). A
    run continued from a saved state (the chunks of `nhjax.run_chunked`) projects onto
    the energy of the state it continues from, the first one's to roundoff.

    **Failures.** Where the gradients of the invariants are linearly dependent, e.g. at
    an equilibrium ($\nabla H = 0$), $GG^T$ is singular: a step that ends on the
    invariant set there (a state at rest stays at rest) is kept as it is; otherwise the
    projection is undefined and the step fails with `nhjax.RESULTS.projection_failed`,
    as it does when the iteration does not converge within `root_find_max_steps`.

    **Arguments:**

    - `solver`: a diffrax solver for `system`'s vector field (e.g. `diffrax.Dopri8()`,
      `diffrax.Tsit5()`); nhjax's own methods are refused, since they keep the
      constraint (or the energy) by construction.
    - `root_find_max_steps`: the most projection iterations per step (default 10).
    """

    interpolation_cls: ClassVar = diffrax.LocalLinearInterpolation

    solver: diffrax.AbstractSolver
    root_find_max_steps: int = eqx.field(static=True)

    def __init__(self, solver: diffrax.AbstractSolver, root_find_max_steps: int = 10):
        if not isinstance(solver, diffrax.AbstractSolver):
            raise ValueError(f"Projection wraps a diffrax solver, got {type(solver).__name__}.")
        if is_nhjax_solver(solver):
            raise ValueError(
                f"Projection wraps diffrax's solvers of the plain vector field; "
                f"{type(solver).__name__} is an nhjax method, which keeps the constraint "
                "(and the discrete-gradient methods the energy) by construction."
            )
        check_positive_int("Projection", "root_find_max_steps", root_find_max_steps)
        if isinstance(solver, diffrax.AbstractRungeKutta) and solver.scan_kind is None:
            # A Runge-Kutta solver's default stage loop has a custom_vjp, through which
            # forward mode cannot go. diffrax.ForwardMode switches the solvers it is given
            # to "lax", but cannot reach inside this wrapper; "bounded" serves forward
            # and reverse mode alike.
            solver = eqx.tree_at(lambda s: s.scan_kind, solver, "bounded", is_leaf=lambda x: x is None)
        self.solver = solver
        self.root_find_max_steps = root_find_max_steps

    @property
    def scan_kind(self):
        """The wrapped Runge-Kutta solver's stage loop: diffrax's wrappers pass
        `isinstance` checks as the solver they wrap, so diffrax.ForwardMode asks."""
        return getattr(self.solver, "scan_kind", None)

    @property
    def term_structure(self):
        return self.solver.term_structure

    def order(self, terms):
        return self.solver.order(terms)

    def keeps_energy(self) -> bool:
        return True

    def keeps_constraint(self) -> bool:
        return True

    def is_symmetric(self) -> bool:
        """The projection of a step's end is not the step's start's: never symmetric
        (GNI §V.4.1), whatever the solver."""
        return False

    def summary(self) -> str:
        return (
            f"{type(self.solver).__name__} at fixed steps on the index-1 ODE, each step's end projected "
            "onto the energy level and the constraint"
        )

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)

    def init(self, terms, t0, t1, y0, args) -> ProjectionState:
        system = unwrapped_system(terms)
        if system.is_forced() and not isinstance(y0, Ledgered):
            raise ValueError(
                "Projection of a system with a force or a dissipation projects onto the energy "
                "balance H(y) = H(y0) + work - dissipated, never onto the initial energy level, and "
                "needs the run's energy ledger (nhjax._ledger) for it: run it with nhjax.integrate or "
                "nhjax.integrate_adaptive, which carry the ledger."
            )
        zero = jnp.array(0, dtype=jnp.int32)
        return ProjectionState(
            inner=self.solver.init(terms, t0, t1, y0, args),
            energy=_level(system, y0, args),
            failure=RESULTS.successful,
            total_steps=zero,
            max_steps=zero,
        )

    def step(self, terms, t0, t1, y0, args, solver_state: ProjectionState, made_jump):
        y_tilde, y_error, _, inner, inner_result = self.solver.step(
            terms, t0, t1, y0, args, solver_state.inner, made_jump
        )
        system = unwrapped_system(terms)
        if isinstance(y_tilde, Ledgered):
            level = solver_state.energy + y_tilde.work - y_tilde.dissipated
            y1, steps, projection_result = self.project(system, y_tilde.state, args, level)
            y1 = Ledgered(y1, y_tilde.work, y_tilde.dissipated)
        else:
            y1, steps, projection_result = self.project(system, y_tilde, args, solver_state.energy)
        failure = first_failure(
            RESULTS.where(inner_result == diffrax.RESULTS.successful, RESULTS.successful, RESULTS.nonfinite_step),
            projection_result,
        )
        # A wrapped solver's state refers to its own end, y_tilde (a Runge-Kutta
        # method that is first same as last carries the field there): it starts again
        # from y1. Stateless solvers (diffrax.Dopri8) have nothing to redo.
        if inner is not None:
            inner = self.solver.init(terms, t1, t1 + (t1 - t0), y1, args)
        state = ProjectionState(
            inner=inner,
            energy=solver_state.energy,
            failure=first_failure(solver_state.failure, failure),
            total_steps=solver_state.total_steps + steps,
            max_steps=jnp.maximum(solver_state.max_steps, steps),
        )
        y1, _, dense_info, state, result = step_return(y0, y1, state, failure)
        return y1, y_error, dense_info, state, result

    def project(self, system: AbstractSystem, y_tilde, args, energy) -> tuple[PyTree[Array], Int[Array, ""], RESULTS]:
        """`y_tilde` projected onto the invariant set of energy `energy`: the projected
        state, the iterations taken, and the code (`projection_failed` if the
        iteration did not converge or its matrix is singular)."""
        flat, unravel = ravel_pytree(y_tilde)
        scales = _row_scales(system, y_tilde, args, energy)

        def scaled_invariants(x):
            return _invariants(system, unravel(x), args, energy) / scales

        directions = jax.jacrev(scaled_invariants)(flat)
        data = _ProjectionData(system, unravel, flat, directions, energy, scales, args)
        fixed = no_gradient(data)
        # Singular where an invariant's gradient vanishes (at an equilibrium,
        # grad H = 0): zeros then, so that a state already on the set passes unchanged,
        # and one that is not fails by not converging, with no NaN on the way.
        gram_inverse = inverse(lax.stop_gradient(directions @ directions.T))
        gram_inverse = jnp.where(jnp.all(jnp.isfinite(gram_inverse)), gram_inverse, 0.0)
        guess = jnp.zeros(directions.shape[0], dtype=flat.dtype)
        root_finder = default_root_finder(flat.dtype)
        assert isinstance(root_finder, PresetChord)
        # The invariants are known only to the rounding of the state they are evaluated
        # at, eps |G| |y| (an angle wound far from the origin), and at least to `atol`;
        # near an equilibrium, where their gradients are small, that rounding moves the
        # multipliers by |(GG^T)^-1| times it at every iteration: corrections of that
        # size are not progress (`PresetChord`'s floor).
        state_rounding = float(jnp.finfo(flat.dtype).eps) * (jnp.abs(lax.stop_gradient(directions)) @ jnp.abs(flat))
        floor = root_finder.atol + ROUNDING_FLOOR * state_rounding
        solution = root_finder.solve(_residual, guess, fixed, gram_inverse, self.root_find_max_steps, floor)
        converged = (solution.result == optx.RESULTS.successful) & jnp.isfinite(solution.residual_size)
        multipliers = _implicit_root(solution.value, data, residual=_residual)
        y1 = unravel(data.y_tilde + data.directions.T @ multipliers)
        result = first_failure(
            RESULTS.where(all_finite(y_tilde) & all_finite(y1), RESULTS.successful, RESULTS.nonfinite_step),
            RESULTS.where(converged, RESULTS.successful, RESULTS.projection_failed),
        )
        return y1, solution.steps, result

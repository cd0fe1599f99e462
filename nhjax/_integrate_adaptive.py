"""Adaptive steps of a standard diffrax solver on the system's own vector field
(`integrate_adaptive`): the non-geometric baseline and the tests' reference."""

import math
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._adjoints import adjoint_or_default
from ._arguments import args_result, check_args, check_save_times, check_switch, default_tolerance, state_dtype, trace_floats
from ._results import first_failure, from_diffrax, nan_where_failed, RESULTS
from ._ledger import observe, run_start
from ._solution import method_outcome, raise_failure, Solution, solution_from_saves
from ._solver.base import is_nhjax_solver
from ._solver.projection import Projection
from ._system import AbstractSystem, in_state_dtype, is_int


def integrate_adaptive(
    system: AbstractSystem,
    y0: PyTree[Array],
    t1: float | Array,
    args: PyTree = None,
    *,
    t0: float | Array = 0.0,
    save_at: Float[Array, " n_saved"] | None = None,
    method: diffrax.AbstractAdaptiveSolver | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 1_000_000,
    throw: bool = True,
    adjoint: diffrax.AbstractAdjoint | None = None,
    solver: diffrax.AbstractAdaptiveSolver | None = None,
) -> Solution:
    r"""Integrate `system`'s vector field from `t0` to `t1` with an adaptive diffrax
    solver, `method` (default `diffrax.Dopri8()`), under a PID step-size controller.

    For a `NonholonomicSystem` the vector field is the index-1 ODE, the multiplier
    eliminated from $\tfrac{d}{dt}[A(q)\partial_pH] = 0$: what a user without
    nhjax's methods would integrate. Neither energy nor constraint is preserved beyond
    the tolerance, and the constraint drifts over long times; at tight tolerance this is
    the high-accuracy reference for convergence tests. With
    `method=nhjax.Projection(diffrax.Dopri8())` every step ends on the energy level and
    the constraint, to roundoff, at Dopri8's order (every saved time is then made a
    step end). For fixed steps of a standard solver (e.g. `diffrax.Tsit5()`) use
    `nhjax.integrate` with that solver.

    **Arguments:** `save_at`, the times to save (default `[t0, t1]`, inside `[t0, t1]`);
    `rtol`, `atol` for the controller (traced ones too: a sweep of tolerances compiles
    once), `None` for the default of the state's dtype,
    `default_tolerance` ($10^{-12}$ in float64; in float32, whose rounding is
    $1.2\cdot10^{-7}$, $100\epsilon = 1.2\cdot10^{-5}$, so that the controller does not
    chase the rounding with ever smaller steps); `max_steps`; `throw` and `adjoint` as
    for `nhjax.integrate`. `solver` is the old name of `method` (the name
    `nhjax.integrate` gives its method), kept for one release with a
    `DeprecationWarning`.
    Returns a `Solution` whose `stats` hold `num_steps` (accepted steps) and
    `num_rejected_steps`, and for a `Projection` its iteration counts. For a system with
    a force or a dissipation, the work and the dissipated energy are integrated with the
    state by the same solver (`Solution.work`, `Solution.dissipated`), and the step-size
    controller weighs them with the state; `nhjax.Projection` then projects onto the
    energy balance.
    """
    if solver is not None:
        if method is not None:
            raise TypeError("integrate_adaptive takes the method once: give method=, not both method= and solver=.")
        warnings.warn(
            "integrate_adaptive's solver= is now method= (as in nhjax.integrate); solver= will be removed.",
            DeprecationWarning,
            stacklevel=2,
        )
        method = solver
    method = diffrax.Dopri8() if method is None else method
    if not isinstance(method, diffrax.AbstractSolver):
        raise ValueError(
            f"method must be a diffrax solver such as diffrax.Dopri8() or nhjax.Projection(diffrax.Dopri8()), "
            f"got {method!r}."
        )
    if is_nhjax_solver(method) and not isinstance(method, Projection):
        # An nhjax method or a composition of one: no error estimate to adapt steps by.
        raise ValueError(
            f"{type(method).__name__} takes fixed steps: run it with nhjax.integrate; integrate_adaptive "
            "takes diffrax's adaptive solvers, alone or in nhjax.Projection."
        )
    if not is_int(max_steps) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
    check_switch("throw", throw)
    system.check_shapes(y0, args)
    check_args(args)
    dtype = state_dtype(y0)
    rtol = default_tolerance(dtype) if rtol is None else rtol
    atol = default_tolerance(dtype) if atol is None else atol
    for value in (rtol, atol):
        if jnp.ndim(value) != 0:
            raise ValueError(f"rtol and atol must be scalars, got shapes {jnp.shape(rtol)} and {jnp.shape(atol)}.")
    if not any(isinstance(value, jax.core.Tracer) for value in (rtol, atol)) and not (float(rtol) > 0 and float(atol) > 0):
        raise ValueError(f"rtol and atol must be positive, got rtol={rtol}, atol={atol}.")
    for name, value in (("t0", t0), ("t1", t1)):
        if not isinstance(value, jax.core.Tracer) and not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {name}={value}.")
    if not isinstance(t1, jax.core.Tracer) and not isinstance(t0, jax.core.Tracer) and not float(t1) > float(t0):
        raise ValueError(f"t1 must be after t0, got t0={t0}, t1={t1}.")
    t0 = jnp.asarray(t0, dtype=dtype)
    t1 = jnp.asarray(t1, dtype=dtype)
    save_at = jnp.stack([t0, t1]) if save_at is None else jnp.asarray(save_at, dtype=dtype)
    if save_at.ndim != 1:
        raise ValueError(f"save_at must be a 1-D array of times, got shape {save_at.shape}.")
    check_save_times(save_at, t0, t1)
    solution = _integrate_adaptive(
        system,
        method,
        y0,
        t0,
        t1,
        save_at,
        in_state_dtype(trace_floats(args), dtype),
        adjoint_or_default(adjoint),
        jnp.asarray(rtol, dtype=dtype),
        jnp.asarray(atol, dtype=dtype),
        max_steps=int(max_steps),
    )
    if throw:
        solution = raise_failure(solution, lambda: f"nhjax.integrate_adaptive failed: {RESULTS[solution.result]}")
    return solution


@eqx.filter_jit
def _integrate_adaptive(system, solver, y0, t0, t1, save_at, args, adjoint, rtol, atol, *, max_steps):
    valid_tolerances = (rtol > 0) & (atol > 0) & jnp.isfinite(rtol) & jnp.isfinite(atol)
    initial_result = first_failure(
        RESULTS.where(valid_tolerances, RESULTS.successful, RESULTS.invalid_tolerance),
        args_result(args),
        system.initial_state_result(y0, args),
    )
    cannot_start = initial_result != RESULTS.successful
    y_start = nan_where_failed(cannot_start, y0, y0)
    # A trajectory that cannot start integrates over no time: from a NaN state the
    # controller would reject every step until max_steps, and under vmap the whole
    # batch would wait for it.
    t_end = jnp.where(cannot_start, t0, t1)
    controller = diffrax.PIDController(rtol=rtol, atol=atol)
    if isinstance(solver, Projection):
        # Its steps end on the invariant set, the linear interpolation between them
        # does not: every saved time is made a step end.
        controller = diffrax.ClipStepSizeController(controller, step_ts=save_at)

    # A forced system's work and dissipated energy are integrated with the state
    # (`nhjax._ledger`).
    solution = diffrax.diffeqsolve(
        system,
        solver,
        t0=t0,
        t1=t_end,
        dt0=None,
        y0=run_start(system, y_start),
        args=args,
        saveat=diffrax.SaveAt(ts=jnp.where(cannot_start, t0, save_at), fn=observe(system), solver_state=True),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    method_failure, statistics = method_outcome(solution.solver_state)
    stats = dict(
        num_steps=solution.stats["num_accepted_steps"],
        num_rejected_steps=solution.stats["num_rejected_steps"],
        **statistics,
    )
    result = first_failure(initial_result, method_failure, from_diffrax(solution.result))
    ts = jnp.where(cannot_start, save_at, solution.ts)
    return solution_from_saves(ts, solution.ys, result, stats, (y0, t0, t1, save_at, args))

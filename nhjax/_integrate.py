"""How steps are strung together: fixed steps through `diffrax.diffeqsolve` for any
method (`integrate`), and adaptive steps of a standard diffrax solver on the system's own
vector field (`integrate_adaptive`), the non-geometric baseline and the tests' reference."""

import numbers
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._results import first_failure, from_diffrax, nan_where_failed, RESULTS
from ._system import AbstractSystem


class Solution(eqx.Module):
    """The result of [`nhjax.integrate`][].

    **Attributes:**

    - `ts`: the save times, shape `(n_saved,)` with `n_saved = n_steps // save_every + 1`.
    - `ys`: the saved states, each leaf with a leading `(n_saved,)` axis.
    - `energy`: the energy at each save, shape `(n_saved,)`.
    - `constraint`: the constraint residual at each save, `(n_saved, k)`, for systems
        with constraints; otherwise `None`.
    - `result`: an `nhjax.RESULTS` code; `nhjax.RESULTS[sol.result]` is its message.
        With `throw=False` a failed trajectory keeps its saves up to the failure and
        holds non-finite values after it.
    - `stats`: `num_steps` (steps taken), `root_find_steps` (root-finder iterations in
        all), `max_root_find_steps` (most iterations in one step).
    """

    ts: Float[Array, " n_saved"]
    ys: PyTree[Array]
    energy: Float[Array, " n_saved"]
    constraint: Float[Array, "n_saved k"] | None
    result: RESULTS
    stats: dict[str, Array]


def _trace_floats(args: PyTree) -> PyTree:
    """Python floats in `args` become arrays, so that changing them does not recompile
    and gradients reach them; ints, bools and everything else stay static."""
    return jax.tree.map(
        lambda leaf: jnp.asarray(leaf) if isinstance(leaf, float) else leaf, args
    )


def check_step_counts(n_steps, save_every) -> None:
    """`ValueError` unless `n_steps` and `save_every` are positive ints and `save_every`
    divides `n_steps` (so that the final state is saved)."""
    if not isinstance(n_steps, numbers.Integral) or n_steps < 1:
        raise ValueError(f"n_steps must be a positive int, got {n_steps!r}.")
    if not isinstance(save_every, numbers.Integral) or save_every < 1:
        raise ValueError(f"save_every must be a positive int, got {save_every!r}.")
    if n_steps % save_every != 0:
        raise ValueError(
            f"save_every={save_every} must divide n_steps={n_steps}, so that the final "
            "state is saved."
        )


def check_step_size(dt) -> None:
    """`ValueError` unless `dt` is a scalar, and positive where it is concrete (a traced
    `dt <= 0` is reported at run time)."""
    if jnp.ndim(dt) != 0:
        raise ValueError(f"dt must be a scalar, got shape {jnp.shape(dt)}.")
    if not isinstance(dt, jax.core.Tracer) and not dt > 0:
        raise ValueError(f"dt must be positive, got dt={dt}.")


def _save_observables(system):
    """The `SaveAt.fn` of both loops: the state and the system's observables."""

    def save(t, y, args):
        del t
        return y, system.observables(y, args)

    return save


def _assemble(ts, saved, result: RESULTS, stats, throw: bool) -> Solution:
    """The `Solution` from diffrax's saves, with a non-finite save reported after any
    earlier failure, and raised if `throw`."""
    ys, observed = saved
    result = first_failure(result, _finite_result(ys))
    if throw:
        ys = result.error_if(ys, result != RESULTS.successful)
    return Solution(
        ts=ts,
        ys=ys,
        energy=observed["energy"],
        constraint=observed.get("constraint"),
        result=result,
        stats=stats,
    )


def _finite_result(ys: PyTree) -> RESULTS:
    """`nonfinite_step` if a saved state is not finite. nhjax's methods report such a
    step themselves, but a diffrax solver at fixed steps does not, and a NaN state
    persists to the final save, which is always saved."""
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(ys)]))
    return RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite_step)


def _adjoint_or_default(adjoint: diffrax.AbstractAdjoint | None) -> diffrax.AbstractAdjoint:
    if adjoint is None:
        return diffrax.RecursiveCheckpointAdjoint()
    if not isinstance(adjoint, diffrax.AbstractAdjoint):
        raise ValueError(f"adjoint must be a diffrax adjoint, got {adjoint!r}.")
    return adjoint


def _state_dtype(y0: PyTree) -> Any:
    return jnp.result_type(*jax.tree.leaves(y0))


def integrate(
    system: AbstractSystem,
    method: diffrax.AbstractSolver,
    y0: PyTree[Array],
    dt: float | Array,
    n_steps: int,
    args: PyTree = None,
    save_every: int = 1,
    progress: bool = False,
    throw: bool = True,
    *,
    t0: float | Array = 0.0,
    check_constraint: bool | Array = True,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> Solution:
    """Integrate `system` with `method` over `n_steps` steps of size `dt` from `t0`.

    The time loop is `diffrax.diffeqsolve` with the steps fixed exactly at
    `t0 + k dt` (`diffrax.StepTo`), saving the initial state and every `save_every`-th
    step (`diffrax.SaveAt(steps=...)`). Works under `jax.jit` and `jax.vmap` (e.g. over
    a batch of `y0`), and compiles once per (system, method, shapes, static arguments):
    `dt`, `t0`, `y0` and float leaves of `args` are traced.

    **Derivatives.** Every output is differentiable with respect to `y0`, `args`, `dt`
    and `t0`. Each step's root is differentiated by the implicit function theorem, with
    the exact Jacobian of the step equations, not through the root finder's iterations,
    so derivatives are those of the exact discrete flow.
    Reverse mode (`jax.grad`, `jax.jacrev`) uses the default `adjoint`,
    `diffrax.RecursiveCheckpointAdjoint()`: memory O(log n_steps) states plus the
    saves, time O(n log n). Forward mode (`jax.jvp`, `jax.jacfwd`) needs
    `adjoint=diffrax.ForwardMode()`. A failed trajectory's outputs have NaN
    derivatives.

    **Arguments:**

    - `system`: e.g. an `nhjax.SkewGradientSystem`.
    - `method`: an nhjax method such as `nhjax.DiscreteGradient()`, or any diffrax solver.
    - `y0`: the initial state, as the system defines it.
    - `dt`: the step size, > 0. Cast to the dtype of `y0`.
    - `n_steps`: the number of steps, a positive int.
    - `args`: parameters passed to every function of the system.
    - `save_every`: save every this many steps; must divide `n_steps`.
    - `progress`: show a progress bar (diffrax's tqdm meter).
    - `throw`: raise on failure. With `throw=False` failures are reported per
        trajectory in `Solution.result` instead.
    - `t0`: the initial time.
    - `check_constraint`: `False` accepts an initial state that violates the constraint
        (e.g. to continue a GONZALEZ-F run, whose constraint residual drifts); every other
        check of the initial state stays. May be traced.
    - `adjoint`: how derivatives pass through the time loop (see above); `None` for
        `diffrax.RecursiveCheckpointAdjoint()`.

    **Errors.** Wrong shapes, a non-integer `n_steps` and a concrete `dt <= 0` raise a
    `ValueError` at once. A non-finite initial state, a structure that is not skew, a
    traced `dt <= 0`, and steps that fail (root find not converged, singular Jacobian,
    non-finite state) raise at run time with the message of their `nhjax.RESULTS` code,
    or with `throw=False` set that code.
    """
    check_step_counts(n_steps, save_every)
    check_step_size(dt)
    system.check_shapes(y0, args)
    dtype = _state_dtype(y0)
    return _integrate(
        system,
        method,
        y0,
        jnp.asarray(dt, dtype=dtype),
        jnp.asarray(t0, dtype=dtype),
        _trace_floats(args),
        jnp.asarray(check_constraint, dtype=bool),
        _adjoint_or_default(adjoint),
        n_steps=int(n_steps),
        save_every=int(save_every),
        progress=bool(progress),
        throw=bool(throw),
    )


@eqx.filter_jit
def _integrate(system, method, y0, dt, t0, args, check_constraint, adjoint, *, n_steps, save_every, progress, throw):
    state_result = system.initial_state_result(y0, args)
    waived = ~check_constraint & (state_result == RESULTS.constraint_violated_initially)
    initial_result = first_failure(
        RESULTS.where(dt > 0, RESULTS.successful, RESULTS.nonpositive_dt),
        RESULTS.where(waived, RESULTS.successful, state_result),
    )
    startable = initial_result == RESULTS.successful
    # A trajectory that cannot start still runs (under vmap its neighbours do), from a
    # NaN state with a harmless step size, so that it stops after one failed step.
    safe_dt = jnp.where(dt > 0, dt, jnp.ones_like(dt))
    y_start = nan_where_failed(~startable, y0, y0)
    step_times = t0 + safe_dt * jnp.arange(n_steps + 1, dtype=dt.dtype)

    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    solution = diffrax.diffeqsolve(
        system,
        method,
        t0=step_times[0],
        t1=step_times[-1],
        dt0=None,
        y0=y_start,
        args=args,
        saveat=diffrax.SaveAt(t0=True, steps=save_every, fn=_save_observables(system), solver_state=True),
        stepsize_controller=diffrax.StepTo(ts=step_times),
        max_steps=n_steps,
        adjoint=adjoint,
        throw=False,
        progress_meter=meter,
    )
    method_state = solution.solver_state
    result = first_failure(
        initial_result,
        getattr(method_state, "failure", RESULTS.successful),
        from_diffrax(solution.result),
    )
    stats = dict(
        num_steps=solution.stats["num_accepted_steps"],
        root_find_steps=getattr(method_state, "total_steps", None),
        max_root_find_steps=getattr(method_state, "max_steps", None),
    )
    return _assemble(solution.ts, solution.ys, result, stats, throw)


def integrate_adaptive(
    system: AbstractSystem,
    y0: PyTree[Array],
    t1: float | Array,
    args: PyTree = None,
    *,
    t0: float | Array = 0.0,
    save_at: Float[Array, " n_saved"] | None = None,
    solver: diffrax.AbstractAdaptiveSolver | None = None,
    rtol: float = 1e-12,
    atol: float = 1e-12,
    max_steps: int = 1_000_000,
    throw: bool = True,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> Solution:
    r"""Integrate `system`'s vector field from `t0` to `t1` with an adaptive diffrax
    solver (default `diffrax.Dopri8()`) under a PID step-size controller.

    For a `NonholonomicSystem` the vector field is the index-1 ODE, the multiplier
    eliminated from $\tfrac{d}{dt}[A(q)\partial_pH] = 0$: what a user without
    nhjax's methods would integrate. Neither energy nor constraint is preserved beyond
    the tolerance, and the constraint drifts over long times; at tight tolerance this is
    the high-accuracy reference for convergence tests. For fixed steps of a standard
    solver (e.g. `diffrax.Tsit5()`) use `nhjax.integrate` with that solver.

    **Arguments:** `save_at`, the times to save (default `[t0, t1]`, inside `[t0, t1]`);
    `rtol`, `atol` for the controller; `max_steps`; `throw` and `adjoint` as for
    `nhjax.integrate`.
    Returns a `Solution` whose `stats` hold `num_steps` (accepted steps) and
    `num_rejected_steps`.
    """
    if not isinstance(max_steps, numbers.Integral) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
    if not (rtol > 0 and atol > 0):
        raise ValueError(f"rtol and atol must be positive, got rtol={rtol}, atol={atol}.")
    if not isinstance(t1, jax.core.Tracer) and not isinstance(t0, jax.core.Tracer) and not t1 > t0:
        raise ValueError(f"t1 must be after t0, got t0={t0}, t1={t1}.")
    system.check_shapes(y0, args)
    dtype = _state_dtype(y0)
    t0 = jnp.asarray(t0, dtype=dtype)
    t1 = jnp.asarray(t1, dtype=dtype)
    save_at = jnp.stack([t0, t1]) if save_at is None else jnp.asarray(save_at, dtype=dtype)
    if save_at.ndim != 1:
        raise ValueError(f"save_at must be a 1-D array of times, got shape {save_at.shape}.")
    return _integrate_adaptive(
        system,
        diffrax.Dopri8() if solver is None else solver,
        y0,
        t0,
        t1,
        save_at,
        _trace_floats(args),
        _adjoint_or_default(adjoint),
        rtol=float(rtol),
        atol=float(atol),
        max_steps=int(max_steps),
        throw=bool(throw),
    )


@eqx.filter_jit
def _integrate_adaptive(system, solver, y0, t0, t1, save_at, args, adjoint, *, rtol, atol, max_steps, throw):
    initial_result = system.initial_state_result(y0, args)
    y_start = nan_where_failed(initial_result != RESULTS.successful, y0, y0)

    solution = diffrax.diffeqsolve(
        system,
        solver,
        t0=t0,
        t1=t1,
        dt0=None,
        y0=y_start,
        args=args,
        saveat=diffrax.SaveAt(ts=save_at, fn=_save_observables(system)),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    result = first_failure(initial_result, from_diffrax(solution.result))
    stats = dict(
        num_steps=solution.stats["num_accepted_steps"],
        num_rejected_steps=solution.stats["num_rejected_steps"],
    )
    return _assemble(solution.ts, solution.ys, result, stats, throw)

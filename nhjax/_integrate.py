"""How steps are strung together: fixed steps of any method (`integrate`), by nhjax's own
loop (`nhjax._fixed_steps`) or, with a progress meter or a diffrax adjoint, by
`diffrax.diffeqsolve`; the two give the same states, codes and statistics. Beside it:
what a run returns (`nhjax._solution`), the checks of its arguments
(`nhjax._arguments`), its step times (`nhjax._step_times`), how it is differentiated
(`nhjax._adjoints`), and adaptive steps (`nhjax._integrate_adaptive`).

**What a step costs.** For the implicit methods, the method's root find: for GONZALEZ-R
the chord matrix and a few residuals (see `nhjax._solver.gonzalez_r`); around it the
loop adds its bookkeeping and, at each save, the energy and constraint residual. The
checks of the start and of the saves cost compile time only, as does diffrax's
end-time clipping where diffrax's loop runs. `python benchmarks/gonzalez_r.py` times
the loop against a bare `lax.scan` of the same steps.

Derivatives of a run with an nhjax method come from its stored roots
(`nhjax._replay`): the run once by the root finder, keeping each step's root, then per
step one replay of the step from its root and the transpose (reverse mode) or the
tangent (forward mode) of its linearisation, with no root finder in the derivative.
The derivative rule wraps the compiled run, so that the derivative program of a
replayed run never traces diffrax's loop: it holds the recording scan (the step and its
bookkeeping) and the replay's linearisation and transpose. `python
benchmarks/gradients.py` measures the time, compile time and peak memory of reverse and
forward mode against the forward run, and against diffrax's checkpointed adjoints;
`python benchmarks/suite.py` the forward steps of every method.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from ._adjoints import checked_adjoint, default_adjoint, replays_derivatives
from ._arguments import args_result, check_args, check_constraint_flag, check_method, check_step_counts, check_step_size, check_switch, state_dtype, trace_floats
from ._fixed_steps import fixed_step_run
from ._replay import replayed_run
from ._results import first_failure, from_diffrax, nan_where_failed, RESULTS
from ._ledger import observe, run_start
from ._solution import method_outcome, nonfinite_saves, raise_failure, Solution, solution_from_saves
from ._step_times import FixedStepTimes, step_time
from ._system import AbstractSystem, in_state_dtype


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
    max_steps: int | None = None,
) -> Solution:
    """Integrate `system` with `method` over `n_steps` steps of size `dt` from `t0`.

    The steps land exactly at `t0 + k dt` (`nhjax._step_times.step_time`); the run
    saves the initial state and every `save_every`-th step. The time loop is nhjax's
    own loop of the method's steps (`nhjax._fixed_steps`), or, with `progress=True` or
    a diffrax `adjoint`, `diffrax.diffeqsolve` with the same steps, with the same
    results. Works under `jax.jit` and `jax.vmap` (e.g. over
    a batch of `y0`), and compiles once per (system, method, shapes, static arguments):
    `dt`, `t0`, `y0` and float leaves of `args` are traced.

    **Derivatives.** Every output is differentiable with respect to `y0`, `args`, `dt`
    and `t0`. Each step's root is differentiated by the implicit function theorem, with
    the exact Jacobian of the step equations, not through the root finder's iterations,
    so derivatives are those of the exact discrete flow.
    With the default `adjoint=None` and an nhjax method, reverse and forward mode
    (`jax.grad`, `jax.jacrev`, `jax.jvp`, `jax.jacfwd`) take the run once with the
    root finder, store each step's root, and differentiate the steps replayed from
    their roots (`nhjax._replay`): time O(n), memory O(n) within 32 MiB per
    trajectory. Longer runs, compositions and diffrax solvers use `default_adjoint`: a
    `diffrax.RecursiveCheckpointAdjoint` with a checkpoint at every step where they
    fit in 32 MiB per trajectory, time O(n); beyond that O(log n_steps) checkpoints,
    time O(n log n); forward mode there needs `adjoint=diffrax.ForwardMode()`. A
    failed trajectory's outputs, the saves before the failure included, have NaN
    derivatives with respect to all of `y0`, `args`, `dt` and `t0`, never
    finite-looking wrong ones; under `vmap` its neighbours keep theirs.

    Second derivatives need forward mode inside: `jax.jacfwd(jax.jacfwd(f))` and
    `jax.jacrev(jax.jacfwd(f))` are exact. With reverse mode inside (`jax.hessian`,
    `jax.jacrev(jax.grad(f))`, `jax.jacfwd(jax.grad(f))`) JAX's partial evaluation of
    the time loop drops each step's implicit derivative before the outer derivative
    sees it; rather than wrong values (they were 1-180% off on the gearbox) these
    second derivatives are NaN (`nhjax._solver.base._nan_derivative`).

    **Arguments:**

    - `system`: e.g. an `nhjax.SkewGradientSystem`.
    - `method`: an nhjax method such as `nhjax.DiscreteGradient()`, or any diffrax solver.
    - `y0`: the initial state, as the system defines it.
    - `dt`: the step size, > 0. Cast to the dtype of `y0`.
    - `n_steps`: the number of steps, a positive int; with `max_steps`, any integer
        scalar in `[1, max_steps]`, traced ones included.
    - `args`: parameters passed to every function of the system. Their real
        floating-point leaves are cast to the dtype of `y0`, as `dt` is.
    - `save_every`: save every this many steps; must divide `n_steps` (with
        `max_steps`: `max_steps`).
    - `progress`: show a progress bar (diffrax's tqdm meter; not in the replayed
        runs of derivatives).
    - `throw`: raise on failure. With `throw=False` failures are reported per
        trajectory in `Solution.result` instead.
    - `t0`: the initial time.
    - `check_constraint`: `False` accepts an initial state that violates the constraint
        (e.g. to continue a GONZALEZ-F run, whose constraint residual drifts); every other
        check of the initial state stays. May be traced.
    - `adjoint`: how derivatives pass through the time loop (see above); `None` for
        the replay from stored roots or `default_adjoint`'s choice. A diffrax adjoint
        differentiates diffrax's loop: `diffrax.RecursiveCheckpointAdjoint()` keeps the
        memory at O(log n_steps) states whatever the run's length or batch.
    - `max_steps`: a static bound on `n_steps`, which may then be traced, so that one
        compilation serves every number of steps up to it: a sweep of step sizes to a
        fixed end time (an order study, `jax.vmap` over `dt` and `n_steps` included)
        compiles once. The saves are those of a run of `max_steps` steps: save $i$
        holds the state after min(i s, n) steps (s = `save_every`, n =
        `n_steps`) at its time, so that `ys[-1]` is always the final state and saves
        past the end repeat it. The run takes $n$ steps; its derivatives by replay
        (above) walk all `max_steps`, holding the state after the end.

    **Errors.** Wrong shapes, a method for another kind of system, a non-integer
    `n_steps`, and a concrete `dt` that is not positive and finite, `t0` or `args` leaf
    that is not finite raise a `ValueError` at once. Everything else is a
    `nhjax.RESULTS` code (the README lists them): with `throw=False` it is set per
    trajectory; with `throw=True` a concrete call raises a `RuntimeError` with its
    message and the step and time of the failure, and a traced one (under `jit`,
    `vmap`, `grad`) a runtime error with its message.
    """
    check_step_counts(n_steps, save_every, max_steps)
    check_step_size(dt, t0)
    check_constraint_flag(check_constraint)
    check_switch("throw", throw)
    check_switch("progress", progress)
    check_args(args)
    system.check_shapes(y0, args)
    check_method(system, method)
    dtype = state_dtype(y0)
    dt, t0 = jnp.asarray(dt, dtype=dtype), jnp.asarray(t0, dtype=dtype)
    solution = _integrate(
        system,
        method,
        y0,
        dt,
        t0,
        in_state_dtype(trace_floats(args), dtype),
        jnp.asarray(check_constraint, dtype=bool),
        checked_adjoint(adjoint),
        # Without a bound the count stays a Python int, static like the bound itself,
        # and the run's loops take exactly that many steps.
        int(n_steps) if max_steps is None else jnp.asarray(n_steps, dtype=jnp.int32),
        max_steps=int(n_steps if max_steps is None else max_steps),
        save_every=int(save_every),
        progress=bool(progress),
    )
    if throw:
        solution = raise_failure(solution, lambda: describe_fixed_step_failure(solution, dt, t0, n_steps))
    return solution


def describe_fixed_step_failure(solution: Solution, dt, t0, n_steps) -> str:
    """Where a concrete single run failed, and why."""
    message = RESULTS[solution.result]
    bad = np.asarray(nonfinite_saves((solution.ys, solution.energy)))
    if bad[0]:
        return f"nhjax.integrate could not start: {message}"
    steps = int(solution.stats["num_steps"])
    if steps < n_steps:  # an nhjax method stops at the step that failed
        start, end = float(t0 + (steps - 1) * dt), float(t0 + steps * dt)
        where = f"step {steps} of {n_steps} (t = {start:g} to {end:g})"
        substep = int(solution.stats.get("failed_substep", -1))
        if substep >= 0:
            stages = solution.stats["substep_root_find_steps"].shape[-1]
            where += f", substep {substep + 1} of {stages}"
        return f"nhjax.integrate failed at {where}: {message}"
    first = int(np.argmax(bad))
    return (
        f"nhjax.integrate failed: the save at t = {float(solution.ts[first]):g} is not "
        f"finite (step {steps} of {n_steps}): {message}"
    )


def _integrate(system, method, y0, dt, t0, args, check_constraint, adjoint, n_steps, *, max_steps, save_every, progress):
    """The run, differentiated through diffrax's loop with a given `adjoint`, or else by
    nhjax's own rule (`_integrate_differentiably`)."""
    static = dict(max_steps=max_steps, save_every=save_every)
    if adjoint is None:
        return _integrate_with_derivative_rule(
            system, method, y0, dt, t0, args, check_constraint, n_steps, progress=progress, **static
        )
    return _integrate_by_diffrax(
        system, method, y0, dt, t0, args, check_constraint, adjoint, n_steps, progress=progress, **static
    )


@eqx.filter_custom_jvp
def _integrate_with_derivative_rule(
    system, method, y0, dt, t0, args, check_constraint, n_steps, *, max_steps, save_every, progress
):
    """The run by nhjax's fixed-step loop (`nhjax._fixed_steps`; diffrax's loop for a
    progress meter), with the derivatives of `_integrate_differentiably`.

    The derivative rule sits outside the compiled run, so that a derivative program
    traces only the rule: JAX traces a jitted function's body whole before it
    differentiates it, and the loop it would trace here is not differentiated."""
    if progress:
        adjoint = diffrax.RecursiveCheckpointAdjoint()  # never differentiated: the rule replaces it
        return _integrate_by_diffrax(
            system, method, y0, dt, t0, args, check_constraint, adjoint, n_steps,
            max_steps=max_steps, save_every=save_every, progress=progress,
        )
    return _integrate_by_fixed_steps(
        system, method, y0, dt, t0, args, check_constraint, n_steps, max_steps=max_steps, save_every=save_every
    )


@_integrate_with_derivative_rule.def_jvp
def _integrate_with_derivative_rule_jvp(primals, tangents, *, max_steps, save_every, progress):
    del progress
    differentiable = functools.partial(_integrate_differentiably, max_steps=max_steps, save_every=save_every)
    return eqx.filter_jvp(differentiable, primals, tangents)


@eqx.filter_jit
def _integrate_differentiably(system, method, y0, dt, t0, args, check_constraint, n_steps, *, max_steps, save_every):
    """The run as its derivatives see it: an nhjax method's run replayed from its
    stored roots (`nhjax._replay.replayed_run`) where they fit the budget
    (`replays_derivatives`), otherwise diffrax's loop with `default_adjoint`."""
    static = dict(max_steps=max_steps, save_every=save_every)
    if replays_derivatives(system, method, y0, args, dt, max_steps, bounded=not isinstance(n_steps, int)):
        run = functools.partial(replayed_run, **static)
    else:
        adjoint = default_adjoint(system, method, y0, args, dt, max_steps)
        run = functools.partial(_diffrax_run, adjoint=adjoint, progress=False, **static)
    return _run_from_start(run, system, method, y0, dt, t0, args, check_constraint, n_steps, **static)


@eqx.filter_jit
def _integrate_by_diffrax(
    system, method, y0, dt, t0, args, check_constraint, adjoint, n_steps, *, max_steps, save_every, progress
):
    static = dict(max_steps=max_steps, save_every=save_every)
    run = functools.partial(_diffrax_run, adjoint=adjoint, progress=progress, **static)
    return _run_from_start(run, system, method, y0, dt, t0, args, check_constraint, n_steps, **static)


@eqx.filter_jit
def _integrate_by_fixed_steps(system, method, y0, dt, t0, args, check_constraint, n_steps, *, max_steps, save_every):
    static = dict(max_steps=max_steps, save_every=save_every)
    return _run_from_start(functools.partial(fixed_step_run, **static), system, method, y0, dt, t0, args, check_constraint, n_steps, **static)


def _diffrax_run(system, method, y_start, dt, t0, args, n_steps, *, adjoint, max_steps, save_every, progress):
    """The fixed-step run by `diffrax.diffeqsolve`: `(ts, (ys, observed), final solver
    state, the run's code, number of steps taken)`, the saves of `max_steps` steps
    (`_held_after_the_end` fills those past `n_steps`)."""
    solution = diffrax.diffeqsolve(
        system,
        method,
        t0=t0,
        t1=t0 + dt * jnp.asarray(n_steps, dtype=dt.dtype),
        dt0=None,
        y0=y_start,
        args=args,
        # t1=True: the final state of a run whose n_steps save_every does not divide.
        saveat=diffrax.SaveAt(t0=True, steps=save_every, t1=True, fn=observe(system), solver_state=True),
        stepsize_controller=FixedStepTimes(t0, dt),
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
        progress_meter=diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter(),
    )
    steps_taken = jnp.asarray(solution.stats["num_accepted_steps"], dtype=int)
    method_failure, _ = method_outcome(solution.solver_state)
    result = first_failure(method_failure, from_diffrax(solution.result))
    return solution.ts, solution.ys, solution.solver_state, result, steps_taken


def _held_after_the_end(ts, saved, n_steps, steps_taken, result, *, save_every):
    """The saves of a run of `n_steps` out of a bound, both loops' alike: save $i$ is the
    state after min(i s, n) steps, so that a complete run repeats its final save
    (the save of step $n$, or diffrax's save at t1) to the end; a run that stopped
    early (a failure) has inf past its last step, as diffrax fills them."""
    slots = jnp.arange(ts.shape[0])
    final = (n_steps + save_every - 1) // save_every
    complete = (steps_taken == n_steps) & (result == RESULTS.successful)
    held = complete & (slots > final)
    unreached = ~complete & (save_every * slots > steps_taken)

    def fill(x):
        shape = (-1,) + (1,) * (x.ndim - 1)
        x = jnp.where(held.reshape(shape), x[final], x)
        return jnp.where(unreached.reshape(shape), jnp.inf, x)

    return fill(ts), jax.tree.map(fill, saved)


def _run_from_start(run, system, method, y0, dt, t0, args, check_constraint, n_steps, *, max_steps, save_every) -> Solution:
    """The checks of the start, then `run`, then the `Solution` of its saves."""
    state_result = system.initial_state_result(y0, args)
    waived = ~check_constraint & (state_result == RESULTS.constraint_violated_initially)
    valid_dt = jnp.isfinite(dt) & (dt > 0)
    valid_n_steps = jnp.asarray((n_steps >= 1) & (n_steps <= max_steps))
    # A trajectory that cannot start still runs (under vmap its neighbours do), from a
    # NaN state at harmless times for one step, so that it stops after one failed step.
    safe_dt = jnp.where(valid_dt, dt, jnp.ones_like(dt))
    if not isinstance(n_steps, int):
        n_steps = jnp.where(valid_n_steps, n_steps, jnp.ones_like(n_steps))
    end = step_time(t0, safe_dt, jnp.asarray(n_steps))
    before_end = step_time(t0, safe_dt, jnp.asarray(n_steps) - 1)
    eps = jnp.finfo(dt.dtype).eps
    # The times t0 + k dt never decrease as k grows, so they are finite if the first
    # and last are, and they increase strictly if dt > 4 eps max(|t0|, |t_n|): each
    # difference t_{k+1} - t_k is dt up to rounding errors of at most 3 eps of that
    # maximum (of dt k and of the sum). Checked in O(1), whatever the bound on n_steps.
    # And no step before the last lands within diffrax's end clipping (100 ulps of
    # t1), which would end its loop early.
    valid_times = (
        jnp.isfinite(t0)
        & jnp.isfinite(end)
        & (safe_dt > 4 * eps * jnp.maximum(jnp.abs(t0), jnp.abs(end)))
        & (end - before_end > 128 * eps * jnp.abs(end))
    )
    t0 = jnp.where(valid_times, t0, jnp.zeros_like(t0))
    initial_result = first_failure(
        RESULTS.where(valid_n_steps, RESULTS.successful, RESULTS.invalid_n_steps),
        RESULTS.where(valid_dt, RESULTS.successful, RESULTS.invalid_dt),
        RESULTS.where(valid_times, RESULTS.successful, RESULTS.invalid_t0),
        args_result(args),
        RESULTS.where(waived, RESULTS.successful, state_result),
    )
    startable = initial_result == RESULTS.successful
    y_start = run_start(system, nan_where_failed(~startable, y0, y0))

    ts, saved, solver_state, run_result, steps_taken = run(system, method, y_start, safe_dt, t0, args, n_steps)
    ts, saved = _held_after_the_end(ts, saved, n_steps, steps_taken, run_result, save_every=save_every)
    _, statistics = method_outcome(solver_state)
    stats = dict(num_steps=steps_taken)
    stats.update(statistics or dict(root_find_steps=None, max_root_find_steps=None))
    result = first_failure(initial_result, run_result)
    return solution_from_saves(ts, saved, result, stats, (y0, dt, t0, args))

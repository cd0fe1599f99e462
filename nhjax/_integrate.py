"""How steps are strung together: fixed steps through `diffrax.diffeqsolve` for any
method (`integrate`), and adaptive steps of a standard diffrax solver on the system's own
vector field (`integrate_adaptive`), the non-geometric baseline and the tests' reference.

**What a step costs.** For the implicit methods, the method's root find: for GONZALEZ-R
the chord matrix and a few residuals (see `nhjax._solver.gonzalez_r`); around it the
loop adds diffrax's bookkeeping and, at each save, the energy and constraint residual.
Outside the loop, diffrax's end-time clipping and the checks of the start and the saves
cost compile time only. `python benchmarks/gonzalez_r.py` times the loop against a bare
`lax.scan` of the same steps.

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
import math
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PyTree

from ._replay import replay_storage_bytes, replayed_run, tree_bytes
from ._results import (
    first_failure, from_diffrax, nan_derivatives_where, nan_where_failed, result_codes, RESULTS, SUCCESS
)
from ._solver.base import AbstractMethod, AbstractMethodState
from ._solver.projection import Projection
from ._system import AbstractSystem, is_int


class Solution(eqx.Module):
    """The result of [`nhjax.integrate`][].

    **Attributes:**

    - `ts`: the save times, shape `(n_saved,)` with `n_saved = n_steps // save_every + 1`
        (`max_steps // save_every + 1` with a bound `max_steps`).
    - `ys`: the saved states, each leaf with a leading `(n_saved,)` axis.
    - `energy`: the energy at each save, shape `(n_saved,)`.
    - `constraint`: the constraint residual at each save, `(n_saved, k)`, for systems
        with constraints; otherwise `None`.
    - `result`: an `nhjax.RESULTS` code; `nhjax.RESULTS[sol.result]` is its message.
        With `throw=False` a failed trajectory keeps its saves up to the failure and
        holds NaN from the first save after it on (a save whose state, energy or
        constraint residual is not finite is a failure), and every output of a failed
        trajectory has NaN derivatives.
    - `stats`: `num_steps` (steps taken), `root_find_steps` (root-finder iterations in
        all), `max_root_find_steps` (most iterations in one step); for an
        `nhjax.Composition`, also `substep_root_find_steps` and `failed_substep` (see
        there).
    """

    ts: Float[Array, " n_saved"]
    ys: PyTree[Array]
    energy: Float[Array, " n_saved"]
    constraint: Float[Array, "n_saved k"] | None
    result: RESULTS
    stats: dict[str, Array]


def trace_floats(args: PyTree) -> PyTree:
    """Python floats in `args` become arrays, so that changing them does not recompile
    and gradients reach them; ints, bools and everything else stay static."""
    return jax.tree.map(
        lambda leaf: jnp.asarray(leaf) if isinstance(leaf, float) else leaf, args
    )


def in_state_dtype(args: PyTree, dtype) -> PyTree:
    """`args` (after `trace_floats`) with its real floating-point arrays in `dtype`, the
    state's: a float64 parameter would otherwise promote a float32 run's states to
    float64 within a step, which the loop's float32 buffers cannot take. Other leaves
    are kept as they are."""

    def cast(leaf):
        if hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating) and leaf.dtype != dtype:
            return jnp.asarray(leaf, dtype=dtype)
        return leaf

    return jax.tree.map(cast, args)


def check_step_counts(n_steps, save_every, max_steps=None) -> None:
    """`ValueError` unless `n_steps` and `save_every` are positive ints and `save_every`
    divides `n_steps` (so that the final state is saved).

    With a bound `max_steps` (a positive int that `save_every` divides), `n_steps` may
    be any integer scalar, traced ones included; a concrete one must lie in
    `[1, max_steps]` (a traced one is checked at run time, code `invalid_n_steps`)."""
    if not is_int(save_every) or save_every < 1:
        raise ValueError(f"save_every must be a positive int, got {save_every!r}.")
    if max_steps is None:
        if not is_int(n_steps) or n_steps < 1:
            raise ValueError(f"n_steps must be a positive int, got {n_steps!r}.")
        if n_steps % save_every != 0:
            raise ValueError(
                f"save_every={save_every} must divide n_steps={n_steps}, so that the final "
                "state is saved."
            )
        return
    if not is_int(max_steps) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
    if max_steps % save_every != 0:
        raise ValueError(f"save_every={save_every} must divide max_steps={max_steps}.")
    if is_int(n_steps):
        concrete = n_steps
    elif (
        hasattr(n_steps, "dtype")
        and jnp.ndim(n_steps) == 0
        and jnp.issubdtype(n_steps.dtype, jnp.integer)
    ):
        concrete = None if isinstance(n_steps, jax.core.Tracer) else int(n_steps)
    else:
        raise ValueError(f"n_steps must be an integer scalar, got {n_steps!r}.")
    if concrete is not None and not 1 <= concrete <= max_steps:
        raise ValueError(f"n_steps must lie in [1, max_steps] = [1, {max_steps}], got {concrete}.")


def check_step_size(dt, t0=0.0) -> None:
    """`ValueError` unless `dt` and `t0` are scalars, `dt` positive and finite and `t0`
    finite where they are concrete (traced ones are checked at run time, with the
    codes `invalid_dt` and `invalid_t0`)."""
    for name, value in (("dt", dt), ("t0", t0)):
        if jnp.ndim(value) != 0:
            raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(value)}.")
    # Concrete values are compared as Python floats: a concrete array closed over by a
    # jitted function would make a comparison traced.
    if not isinstance(dt, jax.core.Tracer) and not (math.isfinite(dt) and float(dt) > 0):
        raise ValueError(f"dt must be positive and finite, got dt={dt}.")
    if not isinstance(t0, jax.core.Tracer) and not math.isfinite(t0):
        raise ValueError(f"t0 must be finite, got t0={t0}.")


def _inexact_leaves_with_paths(tree):
    return [
        (jax.tree_util.keystr(path), leaf)
        for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]
        if isinstance(leaf, (float, complex))
        or (hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.inexact))
    ]


def check_args(args) -> None:
    """`ValueError` naming the first concrete floating-point leaf of `args` that holds
    NaN or inf (traced leaves are checked at run time, code `nonfinite_args`)."""
    for path, leaf in _inexact_leaves_with_paths(args):
        if not isinstance(leaf, jax.core.Tracer) and not bool(np.all(np.isfinite(leaf))):
            raise ValueError(f"args{path} is not finite: {leaf}.")


def args_result(args) -> RESULTS:
    """`nonfinite_args` if a floating-point leaf of `args` holds NaN or inf."""
    leaves = [leaf for _, leaf in _inexact_leaves_with_paths(args)]
    finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(leaf)) for leaf in leaves], dtype=bool))
    return RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite_args)


def _save_observables(system):
    """The `SaveAt.fn` of both loops: the state and the system's observables."""

    def save(t, y, args):
        del t
        return y, system.observables(y, args)

    return save


def _solution_from_saves(ts, saved, result: RESULTS, stats, sources) -> Solution:
    """The `Solution` from diffrax's saves.

    A save whose state or observables (energy, constraint residual) are not finite is a
    failure (`nonfinite_step`, after any earlier failure): nhjax's methods report a
    non-finite step themselves, but a diffrax solver at fixed steps does not, and its
    states can stay finite while the energy overflows. From the first such save on,
    every save is NaN. A failed trajectory's outputs have NaN derivatives with respect
    to everything it was computed from (`sources`: y0, dt, t0, args)."""
    ys, observed = saved
    bad = _nonfinite_saves((ys, observed))
    result = first_failure(
        result, RESULTS.where(jnp.any(bad), RESULTS.nonfinite_step, RESULTS.successful)
    )
    after_bad = jnp.cumsum(bad) > 0
    ys, observed = jax.tree.map(
        lambda x: jnp.where(after_bad.reshape(-1, *(1,) * (x.ndim - 1)), jnp.nan, x),
        (ys, observed),
    )
    failed = result != RESULTS.successful
    ts, ys, observed = nan_derivatives_where(failed, (ts, ys, observed), sources)
    return Solution(
        ts=ts,
        ys=ys,
        energy=observed["energy"],
        constraint=observed.get("constraint"),
        result=result,
        stats=stats,
    )


def _nonfinite_saves(saved: PyTree) -> Bool[Array, " n_saved"]:
    """Per save, whether any leaf of `saved` (each with a leading save axis) is not
    finite."""
    flags = [
        jnp.any(~jnp.isfinite(leaf.reshape(leaf.shape[0], -1)), axis=1)
        for leaf in jax.tree.leaves(saved)
    ]
    return jnp.any(jnp.stack(flags), axis=0)


def _checked_adjoint(adjoint: diffrax.AbstractAdjoint | None) -> diffrax.AbstractAdjoint | None:
    if adjoint is not None and not isinstance(adjoint, diffrax.AbstractAdjoint):
        raise ValueError(f"adjoint must be a diffrax adjoint, got {adjoint!r}.")
    return adjoint


def _adjoint_or_default(adjoint: diffrax.AbstractAdjoint | None) -> diffrax.AbstractAdjoint:
    adjoint = _checked_adjoint(adjoint)
    return diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint


# What one trajectory's checkpoints may occupy when every step keeps one.
CHECKPOINT_BUDGET_BYTES = 32 * 2**20


def default_adjoint(system, method, y0, args, dt, n_steps: int) -> diffrax.RecursiveCheckpointAdjoint:
    r"""The reverse-mode adjoint of a fixed-step run whose derivatives are not replayed
    from stored roots (`replays_derivatives`: a diffrax solver, a composition, or a run
    too long for the budget): a checkpoint at every step where `n_steps` checkpoints of
    the state and the method's solver state fit in `CHECKPOINT_BUDGET_BYTES` (per
    trajectory: under `vmap` a batch of $B$ takes $B$ times as much), otherwise
    diffrax's $O(\log n)$ checkpoints.

    With a checkpoint at every step the backward pass runs each step once more, then
    the transpose of its linearisation; with $c < n$ checkpoints it first recomputes
    steps from the nearest checkpoint, $O(n\log n)$ steps in all for $c = O(\log n)$.
    `python benchmarks/gradients.py` measures them against the forward run."""
    solver_state = jax.eval_shape(lambda: method.init(system, 0 * dt, dt, y0, args))
    if n_steps * tree_bytes((y0, solver_state)) <= CHECKPOINT_BUDGET_BYTES:
        return diffrax.RecursiveCheckpointAdjoint(checkpoints=n_steps)
    return diffrax.RecursiveCheckpointAdjoint()


def replays_derivatives(system, method, y0, args, dt, n_steps: int, bounded: bool = False) -> bool:
    """Whether the derivatives of a run without a given `adjoint` come from its stored
    roots (`nhjax._replay`): for an nhjax method (`nhjax._solver.base.AbstractMethod`)
    whose roots and replayed states for `n_steps` steps fit in
    `CHECKPOINT_BUDGET_BYTES` per trajectory; otherwise `default_adjoint`."""
    if not isinstance(method, AbstractMethod):
        return False
    return n_steps * replay_storage_bytes(system, method, y0, args, dt, bounded) <= CHECKPOINT_BUDGET_BYTES


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
    max_steps: int | None = None,
) -> Solution:
    """Integrate `system` with `method` over `n_steps` steps of size `dt` from `t0`.

    The time loop is `diffrax.diffeqsolve` with the steps fixed exactly at
    `t0 + k dt` (`FixedStepTimes`), saving the initial state and every `save_every`-th
    step (`diffrax.SaveAt(steps=...)`). Works under `jax.jit` and `jax.vmap` (e.g. over
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

    **Errors.** Wrong shapes, a non-integer `n_steps`, and a concrete `dt` that is not
    positive and finite, `t0` or `args` leaf that is not finite raise a `ValueError` at
    once. Everything else is a `nhjax.RESULTS` code (the README lists them): with
    `throw=False` it is set per trajectory; with `throw=True` a concrete call raises a
    `RuntimeError` with its message and the step and time of the failure, and a traced
    one (under `jit`, `vmap`, `grad`) a runtime error with its message.
    """
    check_step_counts(n_steps, save_every, max_steps)
    check_step_size(dt, t0)
    check_args(args)
    system.check_shapes(y0, args)
    dtype = _state_dtype(y0)
    dt, t0 = jnp.asarray(dt, dtype=dtype), jnp.asarray(t0, dtype=dtype)
    solution = _integrate(
        system,
        method,
        y0,
        dt,
        t0,
        in_state_dtype(trace_floats(args), dtype),
        jnp.asarray(check_constraint, dtype=bool),
        _checked_adjoint(adjoint),
        # Without a bound the count stays a Python int, static like the bound itself,
        # and the run's loops take exactly that many steps.
        int(n_steps) if max_steps is None else jnp.asarray(n_steps, dtype=jnp.int32),
        max_steps=int(n_steps if max_steps is None else max_steps),
        save_every=int(save_every),
        progress=bool(progress),
    )
    if throw:
        solution = raise_failure(solution, lambda: _describe_failure(solution, dt, t0, n_steps))
    return solution


def raise_failure(solution: Solution, describe: Callable[[], str]) -> Solution:
    """`solution`, after raising on failure: on the host, a `RuntimeError` with
    `describe()` (which may read `solution`'s concrete values), when the result is
    concrete; otherwise a runtime error in the traced program, with the code's
    message."""
    codes = result_codes(solution.result)
    if isinstance(codes, jax.core.Tracer):
        failed = solution.result != RESULTS.successful
        return eqx.tree_at(lambda s: s.ys, solution, solution.result.error_if(solution.ys, failed))
    if np.any(np.asarray(codes) != SUCCESS):
        raise RuntimeError(describe())
    return solution


def _describe_failure(solution: Solution, dt, t0, n_steps) -> str:
    """Where a concrete single run failed, and why."""
    message = RESULTS[solution.result]
    bad = np.asarray(_nonfinite_saves((solution.ys, solution.energy)))
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


class FixedStepTimes(diffrax.AbstractStepSizeController):
    r"""Steps to exactly $t_k = t_0 + k\,\Delta t$, $k = 1, \dots$, each time computed from
    $k$ as `t0 + dt * k` (the same rounding as `t0 + dt * jnp.arange(n + 1)`).

    What `diffrax.StepTo` does with the array of all step times, without reading that
    array in the loop, which on XLA:CPU slowed every step of a cheap method by a large
    fraction of its cost (the times and states are identical;
    `python benchmarks/gonzalez_r.py` measures the loop's cost per step against a bare
    `lax.scan` of the same steps). The run ends when
    diffrax's loop reaches $t_1 = t_0 + n\,\Delta t$; `integrate` checks beforehand that
    no step lands within diffrax's end-clipping margin (100 ulps) of t1 early."""

    t0: Float[Array, ""]
    dt: Float[Array, ""]

    def wrap(self, direction):
        del direction  # integrate always steps forward
        return self

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        del terms, t0, t1, y0, dt0, args, func, error_order
        return self.t0 + self.dt, jnp.array(2, dtype=jnp.int32)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        del t0, y0, y1_candidate, args, y_error, error_order
        k = controller_state
        next_time = self.t0 + self.dt * k.astype(self.dt.dtype)
        return True, t1, next_time, False, k + 1, diffrax.RESULTS.successful


def _method_outcome(solver_state) -> tuple[RESULTS, dict[str, Array]]:
    """The nhjax code and root-finder statistics in a run's final solver state; success
    and none for a diffrax solver, which reports through `solution.result` alone."""
    if isinstance(solver_state, AbstractMethodState):
        return solver_state.failure, solver_state.statistics()
    return RESULTS.successful, {}


def _integrate(system, method, y0, dt, t0, args, check_constraint, adjoint, n_steps, *, max_steps, save_every, progress):
    """The run, differentiated by replay from its stored roots (`nhjax._replay`) where
    `replays_derivatives` says so, otherwise through diffrax's loop with `adjoint` (or
    `default_adjoint`'s choice)."""
    static = dict(max_steps=max_steps, save_every=save_every)
    if adjoint is None and isinstance(method, AbstractMethod):
        return _integrate_replaying_derivatives(
            system, method, y0, dt, t0, args, check_constraint, n_steps, progress=progress, **static
        )
    return _integrate_by_diffrax(
        system, method, y0, dt, t0, args, check_constraint, adjoint, n_steps, progress=progress, **static
    )


@eqx.filter_custom_jvp
def _integrate_replaying_derivatives(
    system, method, y0, dt, t0, args, check_constraint, n_steps, *, max_steps, save_every, progress
):
    """The run by diffrax's loop, with the derivatives of `_integrate_differentiably`.

    The derivative rule sits outside the compiled run, so that a derivative program
    traces only the rule: JAX traces a jitted function's body whole before it
    differentiates it, and the loop it would trace here is not differentiated."""
    adjoint = diffrax.RecursiveCheckpointAdjoint()  # never differentiated: the rule replaces it
    return _integrate_by_diffrax(
        system, method, y0, dt, t0, args, check_constraint, adjoint, n_steps,
        max_steps=max_steps, save_every=save_every, progress=progress,
    )


@_integrate_replaying_derivatives.def_jvp
def _integrate_replaying_derivatives_jvp(primals, tangents, *, max_steps, save_every, progress):
    del progress
    differentiable = functools.partial(_integrate_differentiably, max_steps=max_steps, save_every=save_every)
    return eqx.filter_jvp(differentiable, primals, tangents)


@eqx.filter_jit
def _integrate_differentiably(system, method, y0, dt, t0, args, check_constraint, n_steps, *, max_steps, save_every):
    """The run of an nhjax method as its derivatives see it: replayed from its stored
    roots (`nhjax._replay.replayed_run`) where they fit the budget
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
    if adjoint is None:  # chosen here, once per compilation
        adjoint = default_adjoint(system, method, y0, args, dt, max_steps)
    static = dict(max_steps=max_steps, save_every=save_every)
    run = functools.partial(_diffrax_run, adjoint=adjoint, progress=progress, **static)
    return _run_from_start(run, system, method, y0, dt, t0, args, check_constraint, n_steps, **static)


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
        saveat=diffrax.SaveAt(t0=True, steps=save_every, t1=True, fn=_save_observables(system), solver_state=True),
        stepsize_controller=FixedStepTimes(t0, dt),
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
        progress_meter=diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter(),
    )
    steps_taken = jnp.asarray(solution.stats["num_accepted_steps"], dtype=int)
    method_failure, _ = _method_outcome(solution.solver_state)
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
    step_times = t0 + safe_dt * jnp.arange(max_steps + 1, dtype=dt.dtype)
    end, before_end = step_times[n_steps], step_times[n_steps - 1]
    in_run = jnp.arange(max_steps + 1) <= n_steps
    # Increasing, and no step before the last within diffrax's end clipping (100 ulps
    # of t1), which would end the loop early.
    end_margin = 128 * jnp.finfo(dt.dtype).eps * jnp.abs(end)
    valid_times = (
        jnp.all(jnp.isfinite(step_times) | ~in_run)
        & jnp.all((jnp.diff(step_times) > 0) | ~in_run[1:])
        & (end - before_end > end_margin)
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
    y_start = nan_where_failed(~startable, y0, y0)

    ts, saved, solver_state, run_result, steps_taken = run(system, method, y_start, safe_dt, t0, args, n_steps)
    ts, saved = _held_after_the_end(ts, saved, n_steps, steps_taken, run_result, save_every=save_every)
    _, statistics = _method_outcome(solver_state)
    stats = dict(num_steps=steps_taken)
    stats.update(statistics or dict(root_find_steps=None, max_root_find_steps=None))
    result = first_failure(initial_result, run_result)
    return _solution_from_saves(ts, saved, result, stats, (y0, dt, t0, args))


def _check_save_times(save_at, t0, t1) -> None:
    """Raise a `ValueError` unless the concrete `save_at` is finite, non-decreasing and
    inside [t0, t1] (diffrax would otherwise stop with an error deep inside the run, or
    with `throw=False` return a failure for a mistake in the call)."""
    if any(isinstance(x, jax.core.Tracer) for x in (save_at, t0, t1)):
        return
    times = np.asarray(save_at)
    if not np.all(np.isfinite(times)):
        raise ValueError(f"save_at must hold finite times, got {times}.")
    if np.any(np.diff(times) < 0):
        raise ValueError(f"save_at must be sorted (non-decreasing), got {times}.")
    if times.size and (times[0] < float(t0) or times[-1] > float(t1)):
        raise ValueError(f"save_at must lie inside [t0, t1] = [{float(t0)}, {float(t1)}], got {times}.")


def integrate_adaptive(
    system: AbstractSystem,
    y0: PyTree[Array],
    t1: float | Array,
    args: PyTree = None,
    *,
    t0: float | Array = 0.0,
    save_at: Float[Array, " n_saved"] | None = None,
    solver: diffrax.AbstractAdaptiveSolver | None = None,
    rtol: float | None = None,
    atol: float | None = None,
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
    the high-accuracy reference for convergence tests. With
    `solver=nhjax.Projection(diffrax.Dopri8())` every step ends on the energy level and
    the constraint, to roundoff, at Dopri8's order (every saved time is then made a
    step end). For fixed steps of a standard solver (e.g. `diffrax.Tsit5()`) use
    `nhjax.integrate` with that solver.

    **Arguments:** `save_at`, the times to save (default `[t0, t1]`, inside `[t0, t1]`);
    `rtol`, `atol` for the controller (traced ones too: a sweep of tolerances compiles
    once), `None` for the default of the state's dtype,
    `default_tolerance` ($10^{-12}$ in float64; in float32, whose rounding is
    $1.2\cdot10^{-7}$, $100\epsilon = 1.2\cdot10^{-5}$, so that the controller does not
    chase the rounding with ever smaller steps); `max_steps`; `throw` and `adjoint` as
    for `nhjax.integrate`.
    Returns a `Solution` whose `stats` hold `num_steps` (accepted steps) and
    `num_rejected_steps`, and for a `Projection` its iteration counts.
    """
    if not is_int(max_steps) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
    system.check_shapes(y0, args)
    check_args(args)
    dtype = _state_dtype(y0)
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
    _check_save_times(save_at, t0, t1)
    solution = _integrate_adaptive(
        system,
        diffrax.Dopri8() if solver is None else solver,
        y0,
        t0,
        t1,
        save_at,
        in_state_dtype(trace_floats(args), dtype),
        _adjoint_or_default(adjoint),
        jnp.asarray(rtol, dtype=dtype),
        jnp.asarray(atol, dtype=dtype),
        max_steps=int(max_steps),
    )
    if throw:
        solution = raise_failure(solution, lambda: f"nhjax.integrate_adaptive failed: {RESULTS[solution.result]}")
    return solution


def default_tolerance(dtype) -> float:
    r"""`integrate_adaptive`'s default rtol and atol for states of `dtype`:
    $\max(10^{-12}, 100\epsilon)$."""
    return max(1e-12, 100 * float(jnp.finfo(dtype).eps))


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

    solution = diffrax.diffeqsolve(
        system,
        solver,
        t0=t0,
        t1=t_end,
        dt0=None,
        y0=y_start,
        args=args,
        saveat=diffrax.SaveAt(
            ts=jnp.where(cannot_start, t0, save_at), fn=_save_observables(system), solver_state=True
        ),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    method_failure, statistics = _method_outcome(solution.solver_state)
    stats = dict(
        num_steps=solution.stats["num_accepted_steps"],
        num_rejected_steps=solution.stats["num_rejected_steps"],
        **statistics,
    )
    result = first_failure(initial_result, method_failure, from_diffrax(solution.result))
    ts = jnp.where(cannot_start, save_at, solution.ts)
    return _solution_from_saves(ts, solution.ys, result, stats, (y0, t0, t1, save_at, args))

"""How steps are strung together: fixed steps through `diffrax.diffeqsolve`."""

import numbers
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._results import RESULTS, first_failure, from_diffrax
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
) -> Solution:
    """Integrate `system` with `method` over `n_steps` steps of size `dt` from `t0`.

    The time loop is `diffrax.diffeqsolve` with the steps fixed exactly at
    `t0 + k dt` (`diffrax.StepTo`), saving the initial state and every `save_every`-th
    step (`diffrax.SaveAt(steps=...)`). Works under `jax.jit`, `jax.vmap` (e.g. over a
    batch of `y0`) and `jax.grad`, and compiles once per (system, method, shapes, static
    arguments): `dt`, `t0`, `y0` and float leaves of `args` are traced.

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

    **Errors.** Wrong shapes, a non-integer `n_steps` and a concrete `dt <= 0` raise a
    `ValueError` at once. A non-finite initial state, a structure that is not skew, a
    traced `dt <= 0`, and steps that fail (root find not converged, singular Jacobian,
    non-finite state) raise at run time with the message of their `nhjax.RESULTS` code,
    or with `throw=False` set that code.
    """
    if not isinstance(n_steps, numbers.Integral) or n_steps < 1:
        raise ValueError(f"n_steps must be a positive int, got {n_steps!r}.")
    if not isinstance(save_every, numbers.Integral) or save_every < 1:
        raise ValueError(f"save_every must be a positive int, got {save_every!r}.")
    if n_steps % save_every != 0:
        raise ValueError(
            f"save_every={save_every} must divide n_steps={n_steps}, so that the final "
            "state is saved."
        )
    if jnp.ndim(dt) != 0:
        raise ValueError(f"dt must be a scalar, got shape {jnp.shape(dt)}.")
    if not isinstance(dt, jax.core.Tracer) and not dt > 0:
        raise ValueError(f"dt must be positive, got dt={dt}.")
    system.check_shapes(y0, args)
    dtype = _state_dtype(y0)
    return _integrate(
        system,
        method,
        y0,
        jnp.asarray(dt, dtype=dtype),
        jnp.asarray(t0, dtype=dtype),
        _trace_floats(args),
        n_steps=int(n_steps),
        save_every=int(save_every),
        progress=bool(progress),
        throw=bool(throw),
    )


@eqx.filter_jit
def _integrate(system, method, y0, dt, t0, args, *, n_steps, save_every, progress, throw):
    initial_result = first_failure(
        RESULTS.where(dt > 0, RESULTS.successful, RESULTS.nonpositive_dt),
        system.initial_state_result(y0, args),
    )
    startable = initial_result == RESULTS.successful
    # A trajectory that cannot start still runs (under vmap its neighbours do), from a
    # NaN state with a harmless step size, so that it stops after one failed step.
    safe_dt = jnp.where(dt > 0, dt, jnp.ones_like(dt))
    y_start = jax.tree.map(lambda y: jnp.where(startable, y, jnp.nan), y0)
    step_times = t0 + safe_dt * jnp.arange(n_steps + 1, dtype=dt.dtype)

    def save(t, y, args):
        del t
        return y, system.observables(y, args)

    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    solution = diffrax.diffeqsolve(
        system,
        method,
        t0=step_times[0],
        t1=step_times[-1],
        dt0=None,
        y0=y_start,
        args=args,
        saveat=diffrax.SaveAt(t0=True, steps=save_every, fn=save, solver_state=True),
        stepsize_controller=diffrax.StepTo(ts=step_times),
        max_steps=n_steps,
        throw=False,
        progress_meter=meter,
    )
    ys, observed = solution.ys
    method_state = solution.solver_state
    result = first_failure(
        initial_result,
        getattr(method_state, "failure", RESULTS.successful),
        from_diffrax(solution.result),
    )
    if throw:
        ys = result.error_if(ys, result != RESULTS.successful)
    stats = dict(
        num_steps=solution.stats["num_accepted_steps"],
        root_find_steps=getattr(method_state, "total_steps", None),
        max_root_find_steps=getattr(method_state, "max_steps", None),
    )
    return Solution(
        ts=solution.ts,
        ys=ys,
        energy=observed["energy"],
        constraint=observed.get("constraint"),
        result=result,
        stats=stats,
    )

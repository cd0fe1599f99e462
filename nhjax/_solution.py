"""What a run returns (`Solution`), how its saves are made and checked, and how a
failed run is reported."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PyTree

from ._results import first_failure, nan_derivatives_where, result_codes, RESULTS, SUCCESS
from ._solver.base import AbstractMethodState


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
        all), `max_root_find_steps` (most iterations in one step); for a method
        that keeps its chord matrix (`nhjax.AbstractMethod.reuses_chord_matrix`), `chord_matrices`
        (the matrices formed); for an `nhjax.Composition`, also
        `substep_root_find_steps` and `failed_substep` (see there).
    - `work`, `dissipated`: the energy the force supplied and the energy the
        dissipation removed from `t0` to each save, shape `(n_saved,)`, so that
        `energy - energy[0] == work - dissipated` (to the method's accuracy). For a
        system with a force or a dissipation (`AbstractSystem.is_forced`) each method
        computes them from its own discrete quantities during the run; for a
        conservative system both are zeros, filled in after the run (nothing is carried
        through the steps), and NaN from a failed trajectory's first bad save on, as
        every other output.
    """

    ts: Float[Array, " n_saved"]
    ys: PyTree[Array]
    energy: Float[Array, " n_saved"]
    constraint: Float[Array, "n_saved k"] | None
    result: RESULTS
    stats: dict[str, Array]
    work: Float[Array, " n_saved"]
    dissipated: Float[Array, " n_saved"]


def solution_from_saves(ts, saved, result: RESULTS, stats, sources) -> Solution:
    """The `Solution` from diffrax's saves.

    A save whose state or observables (energy, constraint residual) are not finite is a
    failure (`nonfinite_step`, after any earlier failure): nhjax's methods report a
    non-finite step themselves, but a diffrax solver at fixed steps does not, and its
    states can stay finite while the energy overflows. From the first such save on,
    every save is NaN. A failed trajectory's outputs have NaN derivatives with respect
    to everything it was computed from (`sources`: y0, dt, t0, args)."""
    ys, observed = saved
    # A conservative run's ledger is zero; it is filled in here, not carried by the steps.
    observed = {"work": jnp.zeros_like(observed["energy"]), "dissipated": jnp.zeros_like(observed["energy"])} | observed
    bad = nonfinite_saves((ys, observed))
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
        work=observed["work"],
        dissipated=observed["dissipated"],
    )


def nonfinite_saves(saved: PyTree) -> Bool[Array, " n_saved"]:
    """Per save, whether any leaf of `saved` (each with a leading save axis) is not
    finite."""
    flags = [
        jnp.any(~jnp.isfinite(leaf.reshape(leaf.shape[0], -1)), axis=1)
        for leaf in jax.tree.leaves(saved)
    ]
    return jnp.any(jnp.stack(flags), axis=0)


def method_outcome(solver_state) -> tuple[RESULTS, dict[str, Array]]:
    """The nhjax code and root-finder statistics in a run's final solver state; success
    and none for a diffrax solver, which reports through `solution.result` alone."""
    if isinstance(solver_state, AbstractMethodState):
        return solver_state.failure, solver_state.statistics()
    return RESULTS.successful, {}


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

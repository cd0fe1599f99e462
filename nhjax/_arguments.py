"""The checks and conversions of what a run is called with: the method for the system,
step counts, step sizes, save times, tolerances and `args`, and the dtype the run
computes in."""

import math
from typing import Any

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree

from ._results import RESULTS
from ._system import is_int, SkewGradientSystem


def trace_floats(args: PyTree) -> PyTree:
    """Python floats in `args` become arrays, so that changing them does not recompile
    and gradients reach them; other leaves are passed on as they are. The run's loops
    still carry Python ints and bools as traced values (the system's functions see
    arrays, not Python objects), so a function that branches on one in Python fails to
    trace: close over it instead, or choose with `jnp.where`."""
    return jax.tree.map(
        lambda leaf: jnp.asarray(leaf) if isinstance(leaf, float) else leaf, args
    )


def check_method(system, method) -> None:
    """`ValueError` unless `method` is a solver (an nhjax method or diffrax's) and
    `system` is of the kind it integrates, its `term_structure` (a class; diffrax's
    solvers take any term): a method for skew-gradient systems given a
    `NonholonomicSystem` failed deep inside its first step, on the tuple (q, p) it
    cannot read."""
    if not isinstance(method, diffrax.AbstractSolver):
        raise ValueError(
            f"method must be an nhjax method such as nhjax.GonzalezR() or a diffrax solver, got {method!r}."
        )
    kind = getattr(method, "term_structure", None)
    if isinstance(kind, type) and not isinstance(system, kind):
        hint = ""
        if kind is SkewGradientSystem and hasattr(system, "reduced"):
            hint = " Its reduced form, system.reduced(signs), is one."
        raise ValueError(f"{type(method).__name__} integrates a {kind.__name__}, got a {type(system).__name__}.{hint}")


def check_step_counts(n_steps, save_every, max_steps=None) -> None:
    """`ValueError` unless `n_steps` and `save_every` are positive ints and `save_every`
    divides `n_steps` (so that the final state is saved).

    With a bound `max_steps` (a positive int that `save_every` divides), `n_steps` may
    be any integer scalar, traced ones included; a concrete one must lie in
    `[1, max_steps]` (a traced one is checked at run time, code `invalid_n_steps`)."""
    if not is_int(save_every) or save_every < 1:
        raise ValueError(f"save_every must be a positive int, got {save_every!r}.")
    if max_steps is None:
        if isinstance(n_steps, jax.core.Tracer):
            raise ValueError(
                "n_steps must be a positive int, got a traced value: a traced number of steps needs "
                "max_steps, a static bound on it."
            )
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


def check_switch(name: str, value) -> None:
    """`ValueError` unless the option `name` (`throw`, `progress`) is True or False: a
    string such as "False" would have been taken for True."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}.")


def check_constraint_flag(check_constraint) -> None:
    """`ValueError` unless `check_constraint` is a bool or a boolean scalar (traced ones
    too): a string was taken for True."""
    if isinstance(check_constraint, bool):
        return
    if not (hasattr(check_constraint, "dtype") and jnp.ndim(check_constraint) == 0 and check_constraint.dtype == bool):
        raise ValueError(f"check_constraint must be True, False or a boolean scalar, got {check_constraint!r}.")


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


def state_dtype(y0: PyTree) -> Any:
    return jnp.result_type(*jax.tree.leaves(y0))


def check_save_times(save_at, t0, t1) -> None:
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


def default_tolerance(dtype) -> float:
    r"""`integrate_adaptive`'s default rtol and atol for states of `dtype`:
    $\max(10^{-12}, 100\epsilon)$."""
    return max(1e-12, 100 * float(jnp.finfo(dtype).eps))

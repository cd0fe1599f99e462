"""Result codes of `nhjax.integrate`: diffrax's, plus the checks nhjax makes itself."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, PyTree


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Per-trajectory outcome of [`nhjax.integrate`][]. Under `jax.vmap` each trajectory
    has its own code; `nhjax.RESULTS[code]` is its message."""

    nonfinite_initial_state = "The initial state contains NaN or inf."
    nonfinite_args = "The parameters args contain NaN or inf."
    invalid_dt = "The step size dt must be positive and finite."
    invalid_t0 = (
        "The step times t0 + k dt must be finite and strictly increasing: t0 is not "
        "finite, or the times are so large that adding dt barely changes them in "
        "floating point (dt must exceed 4 eps max(|t0|, |t_n|)), or changes them by "
        "less than the rounding allowed at the end of the run."
    )
    nonfinite_initial_evaluation = (
        "The system's functions return NaN or inf at the initial state (the "
        "Hamiltonian, its gradient, the structure matrix or the constraint matrix): "
        "check the parameters args, e.g. for a negative mass under a square root."
    )
    structure_not_skew = (
        "structure(x, args) is not skew-symmetric at the initial state, so the flow "
        "would not conserve the Hamiltonian."
    )
    hamiltonian_not_mechanical = (
        "hamiltonian(q, p, args) is not of mechanical type 1/2 p^T M(q)^-1 p + V(q) at "
        "the initial state: it is not quadratic in p, has a term linear in p, or its "
        "Hessian in p is not symmetric positive definite."
    )
    lagrangian_not_mechanical = (
        "The Lagrangian of NonholonomicSystem.from_lagrangian is not of mechanical type "
        "1/2 qdot^T M(q) qdot - V(q) at the initial state or at a step's end (checked "
        "along the velocity there and two fixed directions): it is not quadratic in qdot, "
        "has a term linear in qdot, or its Hessian in qdot, the mass matrix M(q), is not "
        "symmetric positive definite (a singular M among them). Its Legendre transform "
        "would describe another system; the saved states from there on are not finite."
    )
    constraints_rank_deficient = (
        "The constraint matrix A(q) lost full row rank: a Householder pivot vanished "
        "relative to |A| at the start or at a step's end, or the Householder frame of "
        "ker A degenerated between a step's ends (A lost rank within the step). The "
        "constraint distribution has no smooth frame there. The saved states from "
        "that point on are not finite."
    )
    constraint_violated_initially = (
        "The initial momentum violates the constraint A(q) dH/dp(q, p) = 0 beyond "
        "1000 eps; project it first, e.g. with NonholonomicSystem.project_momentum."
    )
    root_find_not_converged = (
        "The implicit equations of a step were not solved to tolerance within the "
        "method's `root_find_max_steps` iterations (or the iteration diverged), with "
        "the system's functions finite at every iterate and A(q) of full rank at the "
        "last. Try a smaller dt, or a larger `root_find_max_steps`. The saved states "
        "from the failed step on are not finite."
    )
    root_find_singular = (
        "The Jacobian of a step's implicit equations was singular. Try a smaller dt. "
        "The saved states from the failed step on are not finite."
    )
    projection_failed = (
        "The projection of a step's end onto the energy level and the constraint "
        "(nhjax.Projection) did not converge: the gradients of the invariants are "
        "(nearly) linearly dependent there, e.g. at an equilibrium, where the gradient "
        "of H vanishes, or the step left the invariant set too far to be brought back. "
        "Try a smaller step or tolerance. The saved states from the failed step on are "
        "not finite."
    )
    nonfinite_step = (
        "A step produced a non-finite state, energy or constraint residual (NaN or "
        "inf), or the system's functions returned NaN or inf during a step: the "
        "solution blew up, or left the region where the system is defined. The saved "
        "states from that step on are not finite."
    )
    invalid_n_steps = "The number of steps n_steps must lie in [1, max_steps]."
    dissipation_not_positive_semidefinite = (
        "The dissipation matrix (D(q, p) of a NonholonomicSystem, R(x) of a "
        "SkewGradientSystem) is not symmetric positive semidefinite at the initial state "
        "(checked to 100 eps relative to its largest entry): it would supply energy "
        "instead of removing it."
    )
    invalid_tolerance = "The tolerances rtol and atol must be positive and finite."


def result_codes(result: RESULTS) -> Array:
    """The integer codes inside `result` (the enumeration item's only leaf), e.g. to
    compare with `SUCCESS` on the host or write to disk."""
    return jax.tree.leaves(result)[0]


# The integer code of success.
SUCCESS = int(result_codes(RESULTS.successful))


_TRANSLATED = (
    (diffrax.RESULTS.nonlinear_max_steps_reached, RESULTS.root_find_not_converged),
    (diffrax.RESULTS.nonlinear_divergence, RESULTS.root_find_not_converged),
    (diffrax.RESULTS.singular, RESULTS.root_find_singular),
    (diffrax.RESULTS.nonfinite, RESULTS.nonfinite_step),
)


def from_diffrax(result: diffrax.RESULTS) -> RESULTS:
    """diffrax's code as an nhjax code, root-find failures named in nhjax's words."""
    translated = RESULTS.promote(result)
    for theirs, ours in _TRANSLATED:
        translated = RESULTS.where(result == theirs, ours, translated)
    return translated


def first_failure(*results: RESULTS) -> RESULTS:
    """The first of `results` that is not successful (or success if none)."""
    out = RESULTS.successful
    for result in reversed(results):
        out = RESULTS.where(result == RESULTS.successful, out, result)
    return out


@jax.custom_jvp
def _zero_with_nan_derivative(failed, sources):
    # A zero computed from `failed`, so that under vmap it is batched as its NaN
    # tangent is: a constant zero's unbatched value beside a batched tangent fails
    # to batch when a jitted vmap is differentiated (jax.jvp of jax.jit(jax.vmap(f))).
    return jnp.where(failed, 0, 0).astype(sources[0].dtype)


@_zero_with_nan_derivative.defjvp
def _zero_with_nan_derivative_jvp(primals, tangents):
    failed, sources = primals
    _, source_tangents = tangents
    zero = _zero_with_nan_derivative(failed, sources)
    blocked = jnp.where(failed, jnp.nan, 0.0).astype(zero.dtype)
    total = sum(jnp.sum(t).astype(zero.dtype) for t in source_tangents)
    return zero, blocked * total


def nan_derivatives_where(failed: Bool[Array, ""], outputs: PyTree, sources: PyTree) -> PyTree:
    """`outputs` unchanged in value, with NaN derivatives with respect to every
    floating-point array in `sources` if `failed` (forward and reverse mode; in reverse
    mode even where the cotangent is zero, since 0 * NaN is NaN).

    The outputs of a failed run are NaN or diffrax's `inf` fill, constants whose
    derivatives would otherwise be zero, and a loss that reads them, or only the saves
    before the failure, would differentiate to a finite, wrong gradient."""
    arrays = [leaf for leaf in jax.tree.leaves(sources) if eqx.is_inexact_array(leaf)]
    if not arrays:
        return outputs
    gate = _zero_with_nan_derivative(failed, arrays)
    return jax.tree.map(
        lambda x: x + gate.astype(x.dtype) if eqx.is_inexact_array(x) else x, outputs
    )


def nan_where_failed(failed: Bool[Array, ""], new: PyTree, source: PyTree) -> PyTree:
    """`new`, or NaN if `failed`, where `new` was computed from `source`: a failed
    output is NaN in value and in its derivatives with respect to `source`
    (`nan_derivatives_where`)."""
    new = jax.tree.map(lambda n: jnp.where(failed, jnp.nan, n), new)
    return nan_derivatives_where(failed, new, source)

"""Result codes of `nhjax.integrate`: diffrax's, plus the checks nhjax makes itself."""

import diffrax
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, PyTree


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Per-trajectory outcome of [`nhjax.integrate`][]. Under `jax.vmap` each trajectory
    has its own code; `nhjax.RESULTS[code]` is its message."""

    nonfinite_initial_state = "The initial state contains NaN or inf."
    nonpositive_dt = "The step size dt must be positive."
    structure_not_skew = (
        "structure(x, args) is not skew-symmetric at the initial state, so the flow "
        "would not conserve the Hamiltonian."
    )
    hamiltonian_not_mechanical = (
        "hamiltonian(q, p, args) is not of mechanical type 1/2 p^T M(q)^-1 p + V(q) at "
        "the initial state: it is not quadratic in p, has a term linear in p, or its "
        "Hessian in p is not symmetric positive definite."
    )
    constraints_rank_deficient = (
        "The constraint matrix A(q) does not have full row rank (a Householder pivot "
        "vanished), so the constraint distribution has no well-defined frame there. "
        "The saved states from that point on are not finite."
    )
    constraint_violated_initially = (
        "The initial momentum violates the constraint A(q) dH/dp(q, p) = 0 beyond "
        "1000 eps; project it first, e.g. with NonholonomicSystem.project_momentum."
    )
    root_find_not_converged = (
        "The implicit equations of a step were not solved to tolerance within the "
        "method's `root_find_max_steps` iterations (or the iteration diverged). Try a "
        "smaller dt, or a larger `root_find_max_steps`. The saved states from the "
        "failed step on are not finite."
    )
    root_find_singular = (
        "The Jacobian of a step's implicit equations was singular. Try a smaller dt. "
        "The saved states from the failed step on are not finite."
    )
    nonfinite_step = (
        "A step produced a non-finite state (NaN or inf): the solution blew up or the "
        "system's functions returned NaN. The saved states from that step on are not "
        "finite."
    )


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
def _nan_derivative_gate(failed, source):
    return jax.tree.map(jnp.zeros_like, source)


@_nan_derivative_gate.defjvp
def _nan_derivative_gate_jvp(primals, tangents):
    failed, source = primals
    _, source_tangent = tangents
    blocked = jnp.where(failed, jnp.nan, 0.0)
    return _nan_derivative_gate(failed, source), jax.tree.map(
        lambda t: t * blocked.astype(t.dtype), source_tangent
    )


def nan_where_failed(failed: Bool[Array, ""], new: PyTree, source: PyTree) -> PyTree:
    """`new`, or NaN if `failed`, where `new` (with the structure of `source`) was
    computed from `source`.

    A failed output is NaN in value and in its derivatives with respect to `source`,
    forward and reverse. Replacing it by a NaN constant alone would give it zero
    derivatives, and a loss that reads it, or only the saves before the failure, would
    differentiate to a finite, wrong gradient."""
    gate = _nan_derivative_gate(failed, source)
    return jax.tree.map(lambda n, g: jnp.where(failed, jnp.nan, n) + g, new, gate)
